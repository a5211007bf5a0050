"""``pyrtu bridge`` with a ``[sparkplug]`` table: the Sparkplug B edge node
(`pyrtu.sparkplug.node.EdgeNode`; docs/sparkplug.md).  Exit status as the JSON
mode's: 2 for a configuration error or a missing library, 3 when a port or the
outbox cannot be opened or the broker refuses the credentials."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from typing import Any

from pyrtu.cli.common import EXIT_OK, EXIT_PORT, EXIT_USAGE, emit, report_error


def run_sparkplug(path: str, bridge: Any, args: argparse.Namespace) -> int:
    """Check or run the edge node of ``bridge`` (a `BridgeConfig` with a
    ``[sparkplug]`` table read from ``path``)."""
    from pathlib import Path

    from pyrtu.poller import ConfigError
    from pyrtu.poller.config import read_config_text
    from pyrtu.sparkplug.config import sparkplug_config

    try:
        text = read_config_text(path)
        cfg = sparkplug_config(bridge, bridge.sparkplug, text, Path(path).resolve().parent)
    except ConfigError as e:
        print(f"pyrtu bridge: config error: {e}", file=sys.stderr)
        if args.json:
            emit({"ok": False, "error": "usage", "exit_code": EXIT_USAGE, "message": str(e)})
        return EXIT_USAGE
    if args.check is not None:
        doc = {
            "ok": True,
            "config": path,
            "mode": "sparkplug",
            "broker": bridge.mqtt.broker,
            "group_id": cfg.group_id,
            "edge_node_id": cfg.edge_node_id,
            "primary_host_id": cfg.primary_host_id,
            "devices": [d.id for d in cfg.devices],
            "metrics": sum(len(d.metrics) for d in cfg.devices),
        }
        if args.json:
            emit(doc)
        else:
            print(
                f"{path}: ok: Sparkplug edge node {cfg.group_id}/{cfg.edge_node_id}, "
                f"{len(cfg.devices)} devices, {doc['metrics']} metrics, broker {bridge.mqtt.broker}"
            )
        return EXIT_OK
    if args.metrics is not None:
        print("pyrtu bridge: error: --metrics is not available with [sparkplug]", file=sys.stderr)
        return EXIT_USAGE
    import importlib.util

    for module, package in (("paho.mqtt.client", "paho-mqtt"), ("google.protobuf", "protobuf")):
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:  # its parent package is missing
            found = False
        if not found:
            print(
                f"pyrtu bridge: error: {package} is missing: pip install 'pyrtu[sparkplug]'",
                file=sys.stderr,
            )
            return EXIT_USAGE
    from pyrtu.drivers.aio import run as aio_run

    return int(aio_run(_serve(cfg, args)))


async def _serve(cfg: Any, args: argparse.Namespace) -> int:
    from pyrtu.outbox.outbox import OutboxError
    from pyrtu.pdu.errors import PortError
    from pyrtu.sparkplug.node import EdgeNode

    node = EdgeNode(cfg)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        try:
            await node.start()
        except OutboxError as e:
            print(f"pyrtu bridge: outbox error: {e}", file=sys.stderr)
            return EXIT_PORT
        except (OSError, ValueError) as e:
            if isinstance(e, PortError):
                raise
            print(f"pyrtu bridge: error: {e}", file=sys.stderr)
            return EXIT_PORT
        waits = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(node.halted.wait())]
        try:
            await asyncio.wait(waits, timeout=args.duration, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()
        await node.stop()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    if node.fatal is not None:
        fatal = node.fatal
        error = fatal if isinstance(fatal, OSError) else ConnectionRefusedError(str(fatal))
        return report_error("bridge", error, args.json)
    if args.json:
        emit({"event": "end", **node.stats()})
    return EXIT_OK


__all__ = ["run_sparkplug"]
