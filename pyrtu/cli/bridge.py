"""``pyrtu bridge --config FILE``: the poller's points to an MQTT broker and back.

Polls the points of a TOML file (the poller's, see ``pyrtu poll --config``) and
publishes them to the broker of its ``[mqtt]`` table: one retained topic per point
(``{prefix}/{edge}/{bus}/{slave}/{point}``, JSON with value, time, quality and
sequence number), the edge's and each slave's status, stats every
``stats_interval``; writes of ``writable`` points from ``{point topic}/set``.
Updates go through a durable outbox on disk: a broker that is down delays them,
never loses them.  See docs/BRIDGE.md.

With a ``[sparkplug]`` table the bridge is a Sparkplug B 3.0 edge node instead
(docs/sparkplug.md; ``pip install 'pyrtu[sparkplug]'``).

``pyrtu bridge --check FILE`` validates a configuration without opening anything.
Exit status: 0 after SIGINT/SIGTERM or --duration (what waits is published
first, up to --drain seconds); 2 for a configuration error (the file, line and
key named) before anything is opened; 3 when a port or the outbox cannot be
opened, the broker refuses the credentials or its certificate does not verify,
or the broker was never reached during the whole run (the updates stay in the
outbox for the next run; an ``mqtts://`` broker that breaks off the TLS handshake
is named with a hint: a plain MQTT broker does).
With ``--json``: one JSON object per event (broker down/up, slave online/offline,
stats) on stdout.  With ``--metrics HOST:PORT``: Prometheus metrics on /metrics and
a health check on /healthz (docs/METRICS.md).
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from collections.abc import Awaitable, Callable, Coroutine
from typing import TYPE_CHECKING, Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_OK,
    EXIT_PORT,
    EXIT_USAGE,
    add_duration_option,
    emit,
    report_error,
    seconds,
    stop_when_stdout_closes,
)
from pyrtu.metrics.address import add_metrics_option, open_metrics

if TYPE_CHECKING:
    from pyrtu.metrics.server import Source
    from pyrtu.outbox.service import OutboxService


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="the TOML file: buses, points and [mqtt]")
    p.add_argument(
        "--check",
        nargs="?",
        const=True,
        default=None,
        metavar="FILE",
        help="validate the configuration (FILE or --config) and exit: nothing is opened",
    )
    add_duration_option(p, "stop after this time (default: on SIGINT/SIGTERM)")
    p.add_argument(
        "--drain",
        type=seconds,
        default=5.0,
        metavar="SECONDS",
        help="at the end, publish what waits for up to this long (default 5 s)",
    )
    p.add_argument(
        "--json", action="store_true", help="one JSON object per event (and the stats) on stdout"
    )
    add_metrics_option(p)


def config_error(e: Exception, args: argparse.Namespace) -> int:
    """A configuration error (file, line and key) said, with ``--json`` as an error
    document too: exit 2."""
    print(f"pyrtu bridge: config error: {e}", file=sys.stderr)
    if args.json:
        emit({"ok": False, "error": "usage", "exit_code": EXIT_USAGE, "message": str(e)})
    return EXIT_USAGE


def checked(args: argparse.Namespace, doc: dict[str, Any], line: str) -> int:
    """``--check``'s verdict on a valid configuration: ``doc`` with ``--json``,
    else ``line``; exit 0."""
    if args.json:
        emit(doc)
    else:
        print(line)
    return EXIT_OK


def _run(args: argparse.Namespace) -> int:
    from pyrtu.poller import ConfigError

    path = args.check if isinstance(args.check, str) else args.config
    if path is None:
        print("pyrtu bridge: error: --config FILE (or --check FILE) is required", file=sys.stderr)
        return EXIT_USAGE
    from pyrtu.bridge.config import load_bridge_config

    try:
        cfg = load_bridge_config(path)
    except ConfigError as e:
        return config_error(e, args)
    if cfg.sparkplug is not None:  # the Sparkplug B edge node (docs/sparkplug.md)
        from pyrtu.cli._bridge_sparkplug import run_sparkplug

        return run_sparkplug(path, cfg, args)
    if args.check is not None:
        m = cfg.mqtt
        doc = {
            "ok": True,
            "config": path,
            "broker": m.broker,
            "edge": m.edge,
            "points": len(cfg.poller.points),
            "buses": len(cfg.poller.buses),
            "writable": sum(1 for p in cfg.poller.points if p.writable),
        }
        return checked(
            args,
            doc,
            f"{path}: ok: {doc['points']} points on {doc['buses']} buses, "
            f"{doc['writable']} writable, broker {m.broker}, edge {m.edge!r}",
        )
    try:
        import paho.mqtt.client  # noqa: F401
    except ImportError:
        print(
            "pyrtu bridge: error: the MQTT client is missing: pip install 'pyrtu[bridge]' "
            "(paho-mqtt)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    return run_output(args, lambda: _serve(cfg, args), len(cfg.poller.buses))


def run_output(
    args: argparse.Namespace, serve: Callable[[], Coroutine[Any, Any, int]], buses: int
) -> int:
    """``serve()`` (a northbound output's run: the JSON bridge's, the Sparkplug
    edge node's) on the event loop, with the server of ``--metrics`` bound first,
    before anything opens (`MetricsError`, exit 2, when it cannot be), as
    ``args.metrics_server`` (None without the option; `serving_metrics` has it
    answer), and closed at the end."""
    from pyrtu.drivers.aio import run as aio_run

    args.metrics_server = open_metrics(args.metrics, "bridge")
    try:
        # (a socket per bus: beyond what select() takes, the epoll loop)
        return int(aio_run(serve(), descriptors=buses))
    finally:
        if args.metrics_server is not None:
            args.metrics_server.close()


def serving_metrics(
    args: argparse.Namespace, source: Callable[[asyncio.AbstractEventLoop], Source]
) -> Callable[[], None]:
    """`serve_output`'s ``started``: the server of ``--metrics`` (if any, from
    `run_output`) answers from then on from ``source(loop)``."""

    def started() -> None:
        if args.metrics_server is not None:
            args.metrics_server.serve(source(asyncio.get_running_loop()))

    return started


async def serve_output(
    output: OutboxService,
    stop: asyncio.Event,
    duration: float | None,
    finish: Callable[[], Awaitable[None]],
    started: Callable[[], None] | None = None,
) -> int | None:
    """Start a northbound output (the JSON bridge, the Sparkplug edge node), run it
    until SIGINT or SIGTERM (or ``stop`` set otherwise), ``duration`` or its halt,
    then ``finish()`` (its stop).  EXIT_PORT, said, when it cannot start (the
    outbox, a file, the poller's ports: a `PortError` is raised, for `guarded` to
    report); None once it ran (its ``fatal`` says whether it halted)."""
    from pyrtu.outbox.outbox import OutboxError
    from pyrtu.pdu.errors import PortError

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    unwatch = stop_when_stdout_closes(loop, stop)  # | head: its reader gone, it ends
    try:
        try:
            await output.start()
        except OutboxError as e:
            print(f"pyrtu bridge: outbox error: {e}", file=sys.stderr)
            return EXIT_PORT
        except (OSError, ValueError) as e:
            if isinstance(e, PortError):  # reported by guarded, as every command does
                raise
            print(f"pyrtu bridge: error: {e}", file=sys.stderr)
            return EXIT_PORT
        if started is not None:
            started()
        waits = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(output.halted.wait())]
        try:
            await asyncio.wait(waits, timeout=duration, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()
        await finish()
    finally:
        unwatch()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    return None


async def _serve(cfg: Any, args: argparse.Namespace) -> int:
    from pyrtu.bridge.bridge import Bridge, BridgeEvent

    bridge = Bridge(cfg)
    stop = asyncio.Event()
    closed = False
    broker_error = ""  # the last connection failure reported

    def on_event(ev: BridgeEvent) -> None:
        nonlocal closed, broker_error
        if ev.kind == "broker_down":
            broker_error = str(ev.detail.get("error", ""))
        if closed:
            return
        try:
            if args.json:
                emit(ev.as_dict())
            elif ev.kind != "stats":
                detail = ", ".join(f"{k} {v}" for k, v in ev.detail.items())
                print(f"pyrtu bridge: {ev.kind}: {detail}", file=sys.stderr, flush=True)
        except BrokenPipeError:
            closed = True  # | head: stop quietly
            stop.set()

    def source(loop: asyncio.AbstractEventLoop) -> Source:
        from pyrtu.metrics.bridge import BridgeSource

        return BridgeSource(bridge, loop)

    bridge.on_event(on_event)
    failed = await serve_output(
        bridge,
        stop,
        args.duration,
        lambda: bridge.stop(drain=args.drain),
        serving_metrics(args, source),
    )
    if failed is not None:
        return failed
    if bridge.fatal is not None:
        return report_error("bridge", as_port_error(bridge.fatal), args.json and not closed)
    if args.json and not closed:
        try:
            emit({"event": "end", **bridge.final_stats})
        except BrokenPipeError:
            pass
    if bridge.reconnects == 0:  # not once connected: nothing was delivered
        waiting = bridge.final_stats.get("outbox_depth", 0)
        never = ConnectionRefusedError(
            f"broker {cfg.mqtt.broker} never reached during the run"
            f" ({broker_error or 'no answer'}); {waiting} updates wait in the outbox"
        )
        return report_error("bridge", never, args.json and not closed)
    return EXIT_OK


def as_port_error(e: BaseException) -> BaseException:
    """An output's fatal error as the OSError `report_error` maps to exit 3."""
    return e if isinstance(e, OSError) else ConnectionRefusedError(str(e))


COMMANDS = (
    subcommand(
        "bridge",
        "the poller's points to an MQTT broker, set commands back (see docs/BRIDGE.md)",
        _configure,
        _run,
        __doc__,
    ),
)

__all__ = [
    "COMMANDS",
    "as_port_error",
    "checked",
    "config_error",
    "run_output",
    "serve_output",
    "serving_metrics",
]
