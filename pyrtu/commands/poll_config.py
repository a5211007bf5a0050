"""``pyrtu poll --config points.toml [--duration S] [--json]``: the poller.

Polls every point of a TOML configuration (see `pyrtu.poller.config`) on all its
buses at once.  On a terminal: a live table of the points (value, age, slave,
bus) and of the buses (utilisation, load).  With ``--json``: one JSON object per
value update, ``{"point", "value", "time", "slave", "bus"}`` (change-only, beyond
each point's deadband), and at the end one ``{"summary": true, ...}`` object with
per-bus utilisation and per-slave counts (requests, responses, timeouts,
exceptions, state).  Otherwise one line per update and the summary at the end.

A configuration error exits with status 2 before any port is opened; a port that
cannot be opened exits 3.  Stops after ``--duration`` seconds or on SIGINT/SIGTERM.

`pyrtu.cli` hands ``pyrtu poll`` over to this module when ``--config`` is given;
``pyrtu poll PORT ADDRESS [COUNT]`` (one range, live statistics) is
`pyrtu.commands.poll`.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from .common import EXIT_OK, EXIT_USAGE, emit, positive_seconds, report_error


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
    p = argparse.ArgumentParser(
        prog="pyrtu poll",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--config", required=True, metavar="FILE", help="the TOML file of buses and points"
    )
    p.add_argument("-d", "--duration", type=positive_seconds, default=None, metavar="SECONDS",
                   help="stop after this time (default: on Ctrl-C)")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object per update and a summary object at the end")  # fmt: skip
    p.add_argument("--all", action="store_true",
                   help="deliver every value read, not only changes")  # fmt: skip
    p.add_argument("--refresh", type=positive_seconds, default=0.5, metavar="SECONDS",
                   help="live table refresh period on a terminal (default 0.5 s)")  # fmt: skip
    return p


def main(argv: Sequence[str], setup_logging: Callable[[int], None] | None = None) -> int:
    """Run ``pyrtu [-v] poll --config ...`` (``argv`` without the program name);
    ``setup_logging(verbosity)`` is the command line's logging set-up."""
    from ..aio import run as aio_run
    from ..poller import ConfigError, Poller, load_config

    args = list(argv)
    verbose = 0
    while args and args[0] != "poll":
        verbose += (
            args[0].count("v") if args[0].startswith("-") and not args[0].startswith("--") else 1
        )
        args.pop(0)
    if setup_logging is not None:
        setup_logging(verbose)
    ns = build_parser().parse_args(args[1:])
    try:
        poller = Poller(load_config(ns.config), changes_only=not ns.all)
    except ConfigError as e:
        print(f"pyrtu poll: config error: {e}", file=sys.stderr)
        return EXIT_USAGE
    try:
        return int(aio_run(_run(poller, ns)))
    except (Exception, KeyboardInterrupt) as exc:
        from ..errors import ModbusError

        if not isinstance(exc, ModbusError | OSError | ValueError | KeyboardInterrupt):
            raise
        return report_error("poll", exc, ns.json)


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class _Table:
    """The live table on a terminal (redrawn in place)."""

    def __init__(self, poller: Any) -> None:
        self.poller = poller
        self.lines = 0

    def draw(self) -> None:
        p = self.poller
        latest = p.latest()
        rows = [f"{'point':32} {'value':>14} {'age':>8}  slave  bus"]
        for name, point in p._points.items():
            u = latest.get(name)
            age = p.age(name)
            value = "-" if u is None else _fmt(u.value)
            rows.append(
                f"{name[:32]:32} {value[:14]:>14} "
                f"{'-' if age is None else f'{age:.2f}s':>8}  {point.slave:5}  {point.bus}"
            )
        for r in p.report():
            state = " OVERLOAD" if r.overloaded else ""
            rows.append(
                f"bus {r.bus}: utilisation {r.utilisation:.1%}, load {r.load:.2f}{state}"
                + (f", lagging: {', '.join(r.lagging[:5])}" if r.lagging else "")
            )
        for s in p.slave_stats():
            d = s.as_dict()
            rows.append(
                f"  slave {d['slave']} on {d['bus']}: {d['state']}, {d['responses']}/"
                f"{d['requests']} answered, p50 {d['latency_p50_ms']} ms, p99 "
                f"{d['latency_p99_ms']} ms"
            )
        out = sys.stdout
        if self.lines:
            out.write(f"\x1b[{self.lines}F")
        out.write("".join(f"\x1b[2K{r}\n" for r in rows))
        out.flush()
        self.lines = len(rows)


async def _run(poller: Any, ns: argparse.Namespace) -> int:
    from ..poller import Update

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    live = sys.stdout.isatty() and not ns.json

    def on_event(ev: Any) -> None:
        if isinstance(ev, Update):
            if ns.json:
                emit(ev.as_dict())
            elif not live:
                stamp = time.strftime("%H:%M:%S", time.localtime(ev.time))
                ms = int(ev.time % 1 * 1000)
                print(f"{stamp}.{ms:03d}  {ev.name} = {_fmt(ev.value)}", flush=True)
        elif not ns.json:
            print(f"pyrtu poll: {_describe(ev)}", file=sys.stderr, flush=True)

    poller.on_event(on_event)
    try:
        await poller.start()
        table = _Table(poller) if live else None
        end = None if ns.duration is None else loop.time() + ns.duration
        while not stop.is_set():
            wait = ns.refresh if end is None else min(ns.refresh, end - loop.time())
            if wait <= 0:
                break
            try:
                await asyncio.wait_for(stop.wait(), wait)
            except TimeoutError:
                pass
            if table is not None:
                table.draw()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        summary = poller.summary()
        await poller.stop()
    if ns.json:
        emit(summary)
    else:
        for b in summary["buses"]:
            print(f"bus {b['bus']}: {b['transactions']} transactions in {b['seconds']} s, "
                  f"utilisation {b['utilisation']:.1%}, load {b['load']:.2f}")  # fmt: skip
        for s in summary["slaves"]:
            print(f"slave {s['slave']} on {s['bus']}: {s['state']}, {s['requests']} requests, "
                  f"{s['responses']} responses, {s['timeouts']} timeouts, "
                  f"{s['exceptions']} exceptions")  # fmt: skip
    return EXIT_OK


def _describe(ev: Any) -> str:
    from ..poller import Overload, PointDropped, SlaveState

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


__all__ = ["build_parser", "main", "wants"]
