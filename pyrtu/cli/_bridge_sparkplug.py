"""``pyrtu bridge`` with a ``[sparkplug]`` table: the Sparkplug B edge node
(`pyrtu.sparkplug.node.EdgeNode`; docs/sparkplug.md).  Exit status as the JSON
mode's: 2 for a configuration error, a missing library or a ``--metrics`` that
cannot be served, 3 when a port or the outbox cannot be opened or the broker
refuses the credentials.  ``--metrics HOST:PORT``: the edge node's metrics
(`pyrtu.metrics.sparkplug`) and health, as the JSON mode's."""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import TYPE_CHECKING, Any

from pyrtu.cli.common import EXIT_OK, EXIT_USAGE, emit, report_error

if TYPE_CHECKING:
    from pyrtu.metrics.server import Source


def run_sparkplug(path: str, bridge: Any, args: argparse.Namespace) -> int:
    """Check or run the edge node of ``bridge`` (a `BridgeConfig` with a
    ``[sparkplug]`` table read from ``path``)."""
    from pathlib import Path

    from pyrtu.cli.bridge import checked, config_error
    from pyrtu.poller import ConfigError
    from pyrtu.poller.config import read_config_text
    from pyrtu.sparkplug.config import sparkplug_config

    try:
        text = read_config_text(path)
        cfg = sparkplug_config(bridge, bridge.sparkplug, text, Path(path).resolve().parent)
    except ConfigError as e:
        return config_error(e, args)
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
        return checked(
            args,
            doc,
            f"{path}: ok: Sparkplug edge node {cfg.group_id}/{cfg.edge_node_id}, "
            f"{len(cfg.devices)} devices, {doc['metrics']} metrics, broker {bridge.mqtt.broker}",
        )
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
    from pyrtu.cli.bridge import run_output

    return run_output(args, lambda: _serve(cfg, args), len(bridge.poller.buses))


async def _serve(cfg: Any, args: argparse.Namespace) -> int:
    from pyrtu.cli.bridge import as_port_error, serve_output, serving_metrics
    from pyrtu.sparkplug.node import EdgeNode

    node = EdgeNode(cfg)

    def source(loop: asyncio.AbstractEventLoop) -> Source:
        from pyrtu.metrics.sparkplug import SparkplugSource

        return SparkplugSource(node, loop)

    started = serving_metrics(args, source)
    failed = await serve_output(node, asyncio.Event(), args.duration, node.stop, started)
    if failed is not None:
        return failed
    if node.fatal is not None:
        return report_error("bridge", as_port_error(node.fatal), args.json)
    if args.json:
        emit({"event": "end", **node.stats()})
    return EXIT_OK


__all__ = ["run_sparkplug"]
