"""``pyrtu poll --config points.toml [--duration S] [--json]``: the poller.

Polls every point of a TOML configuration (see `pyrtu.poller.config`) on all its
buses at once.  On a terminal: a live table of the points (value, age, slave, bus:
as many as fit) and of the buses (port, utilisation, load) and slaves.  With
``--json``: one JSON object per value update, ``{"point", "value", "time",
"slave", "bus"}`` (change-only, beyond each point's deadband, unless ``--all``),
one per event (``"event"``: ``"port"`` up/down, ``"slave"`` online/offline,
``"dropped"``, ``"overload"``), and at the end one ``{"summary": true, ...}``
object (``updates``: the update lines printed; ``values_read``: every value read;
per bus the port's state and utilisation, per slave the counts and state).
Otherwise one line per update, the events on stderr and the summary at the end.
With ``--metrics HOST:PORT``: Prometheus metrics on /metrics and a health check on
/healthz (docs/METRICS.md).

A port that fails (cannot be opened or connected, unplugged, a TCP peer gone) is
reported once and opened again with back-off while the other buses poll on.
Stops after ``--duration`` seconds, on SIGINT/SIGTERM, or quietly (status 0) when
the reader of its output goes away (``| head``).

`pyrtu.cli` hands ``pyrtu poll`` over to this module when ``--config`` is given;
``pyrtu poll PORT ADDRESS [COUNT]`` (one range, live statistics) is
`pyrtu.cli.poll`.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import logging
import os
import signal
import stat
import sys
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from pyrtu._startup import started
from pyrtu.cli.common import (
    EXIT_EXCEPTION,
    EXIT_NO_RESPONSE,
    EXIT_OK,
    EXIT_PORT,
    EXIT_USAGE,
    JsonErrorParser,
    add_duration_option,
    emit,
    error_document,
    jsonable,
    positive_seconds,
    report_error,
    silence_stdout,
)
from pyrtu.cli.live_view import same_terminal, terminal_size
from pyrtu.cli.poll_table import LiveTable, fmt_value, ms
from pyrtu.metrics.address import MetricsError, add_metrics_option, open_metrics

if TYPE_CHECKING:
    from pyrtu.poller import Poller
    from pyrtu.poller.events import Event

#: what the exit status says of the data (``--help`` shows it)
EXIT_STATUS = """\
exit status (the first that applies):
  3  port         a bus's port never worked (cannot be opened or connected),
                  or was down at the end
  4  no response  a slave was not online at the end, or a point was never read
  5  exception    a point was dropped (its slave answered exception 2: no such
                  address)
  0  ok           every port up, every slave online and every point read
  2  usage        bad arguments or a configuration error (before any port opens)
  1  failure      anything else (an internal error)
SIGINT, SIGTERM and --duration end the run normally: the status says what came in.
A closed output pipe (| head) ends it at once with status 0."""


def wants(argv: Sequence[str]) -> bool:
    """Whether a command line is ``pyrtu [-v...] poll ... --config ...``."""
    args = list(argv)
    i = 0
    while i < len(args) and args[i].startswith("-") and args[i] not in ("--",):
        if args[i] in ("-h", "--help", "--version"):
            return False
        i += 1
    if i >= len(args) or args[i] != "poll":
        return False
    return any(a == "--config" or a.startswith("--config=") for a in args[i + 1 :])


def build_parser() -> argparse.ArgumentParser:
    p = JsonErrorParser(
        prog="pyrtu poll",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
        epilog=EXIT_STATUS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--config", required=True, metavar="FILE", help="the TOML file of buses and points"
    )
    add_duration_option(p, "stop after this time (default: on Ctrl-C)")
    p.add_argument("--json", action="store_true",
                   help="one JSON line per update and per event, a summary at the end")  # fmt: skip
    p.add_argument("--all", action="store_true",
                   help="deliver every value read, not only changes")  # fmt: skip
    p.add_argument("--refresh", type=positive_seconds, default=0.5, metavar="SECONDS",
                   help="live table refresh period on a terminal (default 0.5 s)")  # fmt: skip
    add_metrics_option(p)
    return p


def main(argv: Sequence[str], setup_logging: Callable[[int], None] | None = None) -> int:
    """Run ``pyrtu [-v] poll --config ...`` (``argv`` without the program name);
    ``setup_logging(verbosity)`` is the command line's logging set-up."""
    from pyrtu.drivers.aio import run as aio_run
    from pyrtu.poller import ConfigError, Poller, load_config

    args = list(argv)
    verbose = 0
    while args and args[0] != "poll":
        verbose += (
            args[0].count("v") if args[0].startswith("-") and not args[0].startswith("--") else 1
        )
        args.pop(0)
    if setup_logging is not None:
        setup_logging(verbose)
    JsonErrorParser.json_errors = "--json" in args
    ns = build_parser().parse_args(args[1:])
    try:
        poller = Poller(load_config(ns.config), changes_only=not ns.all)
    except ConfigError as e:
        print(f"pyrtu poll: config error: {e}", file=sys.stderr)
        if ns.json:  # errors come as JSON too (README, "--json")
            emit({**error_document(e, EXIT_USAGE), "message": f"config error: {e}"})
        return EXIT_USAGE
    try:  # bound before any port opens: a port in use is a usage error
        ns.metrics_server = open_metrics(ns.metrics, "poll")
    except MetricsError as e:
        print(f"pyrtu poll: error: {e}", file=sys.stderr)
        if ns.json:
            emit(error_document(e, EXIT_USAGE))
        return EXIT_USAGE
    out = Output()
    started()  # Ctrl-C: quiet status 130 until here (pyrtu._startup), a normal end from now
    try:
        # (a port or socket per bus: beyond what select() takes, the epoll loop)
        code = int(aio_run(_run(poller, ns, out), descriptors=poller.descriptors))
    except (Exception, KeyboardInterrupt) as exc:
        from pyrtu.pdu.errors import ModbusError

        if isinstance(exc, BrokenPipeError):
            out.closed = True
        elif not isinstance(exc, ModbusError | OSError | ValueError | KeyboardInterrupt):
            raise
        else:
            code = report_error("poll", exc, False)
            if ns.json and not out.closed:
                out.json(error_document(exc, code))
    finally:
        if ns.metrics_server is not None:
            ns.metrics_server.close()
    if out.closed:
        # the reader went away (| head): Python flushes stdout at exit, so point it
        # at /dev/null for that not to fail too
        silence_stdout()
        return EXIT_OK
    return code


class Output:
    """stdout, which a closed pipe ends quietly: the first write that fails, or the
    reader of a pipe going away (seen by the event loop at once), sets `closed`
    and `stop`; nothing is written after."""

    def __init__(self) -> None:
        self.closed = False
        self.stop: asyncio.Event | None = None
        self._watched: int | None = None

    def write(self, text: str) -> bool:
        if self.closed:
            return False
        try:
            sys.stdout.write(text)
            sys.stdout.flush()
        except BrokenPipeError:
            self._close()
            return False
        return True

    def flush(self) -> None:
        """Nothing: each `write` is flushed (for `pyrtu.cli.live_view.Writer`)."""

    def json(self, doc: dict[str, Any]) -> bool:
        return self.write(json.dumps(jsonable(doc), allow_nan=False) + "\n")

    def _close(self) -> None:
        self.closed = True
        if self.stop is not None:
            self.stop.set()

    def watch(self, loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> None:
        """Stop when stdout is a pipe whose reader closes (its write end then
        reports an error, which the loop's selector sees as readable)."""
        self.stop = stop
        try:
            fd = sys.stdout.fileno()
            if not stat.S_ISFIFO(os.fstat(fd).st_mode):
                return
            loop.add_reader(fd, self._hangup, loop, fd)
        except (OSError, ValueError, io.UnsupportedOperation):
            return  # not a real pipe: the writes tell
        self._watched = fd

    def _hangup(self, loop: asyncio.AbstractEventLoop, fd: int) -> None:
        loop.remove_reader(fd)
        self._watched = None
        self._close()

    def unwatch(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._watched is not None:
            loop.remove_reader(self._watched)
            self._watched = None


def exit_status(summary: dict[str, Any]) -> tuple[int, str]:
    """The exit status of a run (``EXIT_STATUS``) and why, from `Poller.summary`."""
    for b in summary["buses"]:
        if b["port_state"] != "up":
            why = b["port_error"] or "nothing went through it"
            return EXIT_PORT, f"bus {b['bus']}: port {b['port']} {b['port_state']}: {why}"
    for s in summary["slaves"]:
        if s["state"] != "online":
            return EXIT_NO_RESPONSE, f"bus {s['bus']}: slave {s['slave']} {s['state']} at the end"
    if summary["points_unread"]:
        return EXIT_NO_RESPONSE, f"{summary['points_unread']} points never read"
    if summary["dropped_points"]:
        names = ", ".join(summary["dropped_points"][:5])
        more = len(summary["dropped_points"]) - 5
        return EXIT_EXCEPTION, f"points dropped: {names}" + (
            f" and {more} more" if more > 0 else ""
        )
    return EXIT_OK, ""


async def _pause(stop: asyncio.Event, seconds: float) -> None:
    """Wait ``seconds`` or until ``stop`` is set (a timer, not asyncio.wait_for)."""
    loop = asyncio.get_running_loop()
    tick = asyncio.Event()
    timer = loop.call_later(seconds, tick.set)
    waiters = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(tick.wait())]
    try:
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
    finally:
        timer.cancel()
        for w in waiters:
            w.cancel()


async def _run(poller: Poller, ns: argparse.Namespace, out: Output) -> int:
    from pyrtu.poller import Update

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    out.watch(loop, stop)
    table = (
        LiveTable(poller, out, terminal_size(sys.stdout))
        if sys.stdout.isatty() and not ns.json
        else None
    )
    # the table owns the terminal: an event for a stderr on the same terminal is
    # printed through it (above the table, drawn again below), never around it
    through_table = table is not None and same_terminal(sys.stdout, sys.stderr)
    done = False  # after the summary's snapshot nothing more is printed

    def redraw() -> None:
        if table is not None and not stop.is_set() and not out.closed:
            table.draw()

    def on_event(ev: Event) -> None:
        if done or out.closed:
            return
        if isinstance(ev, Update):
            if ns.json:
                out.json(ev.as_dict())
            elif table is None:
                stamp = time.strftime("%H:%M:%S", time.localtime(ev.time))
                ms = int(ev.time % 1 * 1000)
                out.write(f"{stamp}.{ms:03d}  {ev.name} = {fmt_value(ev.value)}\n")
        elif ns.json:
            out.json(ev.as_dict())
        elif table is not None and through_table:
            table.print_above(f"pyrtu poll: {describe(ev)}", sys.stderr)
        else:
            print(f"pyrtu poll: {describe(ev)}", file=sys.stderr, flush=True)

    poller.on_event(on_event)
    if table is not None:
        loop.add_signal_handler(signal.SIGWINCH, redraw)  # resized: fit it at once
    # -v: the log lines for the terminal go through the table too
    view = table.view if table is not None and through_table else None
    logs = _log_handlers_on(sys.stderr) if view is not None else []
    for handler in logs:
        assert view is not None
        handler.setStream(view.above(sys.stderr))
    try:
        await poller.start()
        if ns.metrics_server is not None:
            from pyrtu.metrics.poller import PollerSource

            ns.metrics_server.serve(PollerSource(poller, loop))
        end = None if ns.duration is None else loop.time() + ns.duration
        while not stop.is_set():
            wait = ns.refresh if end is None else min(ns.refresh, end - loop.time())
            if wait <= 0:
                break
            await _pause(stop, wait)
            redraw()
    finally:
        summary = poller.summary()
        done = True
        try:
            await poller.stop()
        finally:
            out.unwatch(loop)
            for handler in logs:
                handler.setStream(sys.stderr)
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGWINCH):
                loop.remove_signal_handler(sig)
    if out.closed:
        return EXIT_OK
    code, why = exit_status(summary)
    if ns.json:
        out.json(summary)
    else:
        _print_summary(out, summary, table is not None)
    if code:
        print(f"pyrtu poll: exit status {code}: {why}", file=sys.stderr, flush=True)
    return code


def _log_handlers_on(stream: Any) -> list[logging.StreamHandler[Any]]:
    """The handlers of pyrtu's log (``-v``) that write to ``stream``."""
    return [
        handler
        for handler in logging.getLogger("pyrtu").handlers
        if isinstance(handler, logging.StreamHandler) and handler.stream is stream
    ]


def _print_summary(out: Output, summary: dict[str, Any], live: bool) -> None:
    lines = [
        f"{summary['updates']} updates {'delivered' if live else 'printed'}, "
        f"{summary['values_read']} values read; "
        f"{summary['points_read']} of {summary['points']} points read"
    ]
    for b in summary["buses"]:
        lines.append(
            f"bus {b['bus']} ({b['port']}): port {b['port_state']}, {b['outages']} outages, "
            f"{b['transactions']} transactions in {b['seconds']} s, "
            f"utilisation {b['utilisation']:.1%}, load {b['load']:.2f}"
            + (f", {b['task_failures']} task failures" if b.get("task_failures") else "")
        )
    for s in summary["slaves"]:
        lines.append(
            f"slave {s['slave']} on {s['bus']}: {s['state']}, {s['requests']} requests, "
            f"{s['responses']} responses, {s['timeouts']} timeouts, "
            f"{s['exceptions']} exceptions, p50 {ms(s['latency_p50_ms'])}"
        )
    if summary["dropped_points"]:
        lines.append("dropped: " + ", ".join(summary["dropped_points"]))
    out.write("".join(line + "\n" for line in lines))


def describe(ev: Event) -> str:
    """An event (not an update) for people."""
    from pyrtu.poller import Overload, PointDropped, PortState, SlaveState
    from pyrtu.poller.driver import describe_port, describe_task_failed
    from pyrtu.poller.events import TaskFailed

    if isinstance(ev, PortState):
        return describe_port(ev)
    if isinstance(ev, TaskFailed):
        return describe_task_failed(ev)
    if isinstance(ev, SlaveState):
        return f"bus {ev.bus}: slave {ev.slave} {'online' if ev.online else 'offline'}"
    if isinstance(ev, PointDropped):
        return f"point {ev.point.name!r} dropped: {ev.reason}"
    if isinstance(ev, Overload):
        if not ev.overloaded:
            return f"bus {ev.bus}: no longer overloaded (load {ev.load:.2f})"
        lag = ", ".join(ev.lagging[:8]) + (" ..." if len(ev.lagging) > 8 else "")
        return f"bus {ev.bus}: OVERLOADED: the rates need {ev.load:.2f}x the wire; lagging: {lag}"
    return str(ev)


__all__ = ["EXIT_STATUS", "Output", "build_parser", "describe", "exit_status", "main", "wants"]
