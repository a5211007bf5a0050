"""``pyrtu bridge``'s metrics: its poller's (`pyrtu.metrics.poller`) and the
bridge's own, read at each scrape from `Bridge.stats` (the figures its ``stats``
topic publishes): the broker connection, what was appended, published and
acknowledged, the outbox's depth, size and the age of its oldest record, drops,
quarantined records, the set commands.

No secret reaches a label or a value: the MQTT user, password and TLS files are
never read here (`Bridge.stats` holds none), and the broker is named only in
``/healthz``'s reason (its URL cannot carry credentials: `pyrtu.bridge.config`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from pyrtu.bridge.bridge import Bridge

from .poller import PollerSource
from .poller import families as poller_families
from .poller import snapshot as poller_snapshot
from .server import on_loop

#: (metric, help, stats key) of the counters both MQTT outputs keep (the JSON
#: bridge and the Sparkplug edge node, `pyrtu.metrics.sparkplug`)
OUTPUT_COUNTERS = (
    (
        "pyrtu_bridge_outbox_dropped",
        "Records dropped: the outbox full (drop-oldest) or refusing (refuse)",
        "drops",
    ),
    ("pyrtu_bridge_broker_connections", "Connections to the broker made", "connections"),
    ("pyrtu_bridge_broker_outages", "Outages of the broker connection", "outages"),
    (
        "pyrtu_bridge_task_failures",
        "Times a background task raised (each restarted on the back-off)",
        "task_failures",
    ),
)
#: (metric, help, `Bridge.stats` key) of the JSON bridge's own counters
COUNTERS = (
    ("pyrtu_bridge_updates", "Records appended to the outbox (values to publish)", "updates"),
    ("pyrtu_bridge_published", "Records handed to the MQTT client", "published"),
    ("pyrtu_bridge_acknowledged", "Records the broker acknowledged", "acknowledged"),
    ("pyrtu_bridge_quarantined", "Records no broker accepts, set aside", "quarantined"),
)
#: the set commands' counters of `Bridge.stats` (``commands``), as ``result`` labels
COMMAND_RESULTS = ("received", "ignored", "executed", "expired", "duplicates", "busy", "failed")


def output_families(stats: dict[str, Any]) -> Iterator[Metric]:
    """The families of an MQTT output, either mode, from its figures keyed as
    `Bridge.stats`'s: ``connected``, ``connections``, ``outages``, ``drops``,
    ``task_failures``, ``outbox_depth``, ``outbox_bytes``, ``oldest_unsent_s``,
    ``commands`` (`SetWriter.stats`)."""
    connected = GaugeMetricFamily(
        "pyrtu_bridge_broker_connected", "1 while connected to the MQTT broker"
    )
    connected.add_metric([], 1 if stats["connected"] else 0)
    yield connected
    for name, documentation, key in OUTPUT_COUNTERS:
        counter = CounterMetricFamily(name, documentation)
        counter.add_metric([], stats[key])
        yield counter
    depth = GaugeMetricFamily(
        "pyrtu_bridge_outbox_depth", "Records in the outbox not yet acknowledged by the broker"
    )
    depth.add_metric([], stats["outbox_depth"])
    size = GaugeMetricFamily("pyrtu_bridge_outbox_bytes", "Bytes of the outbox's segment files")
    size.add_metric([], stats["outbox_bytes"])
    oldest = stats["oldest_unsent_s"]
    age = GaugeMetricFamily(
        "pyrtu_bridge_outbox_oldest_age_seconds",
        "Age of the oldest record not yet acknowledged (0: the outbox is empty)",
    )
    age.add_metric([], 0.0 if oldest is None else oldest)
    yield from (depth, size, age)
    commands = stats["commands"]
    counter = CounterMetricFamily(
        "pyrtu_bridge_commands", "Set commands by what became of them", labels=["result"]
    )
    for result in COMMAND_RESULTS:
        counter.add_metric([result], commands[result])
    yield counter
    waiting = GaugeMetricFamily("pyrtu_bridge_commands_waiting", "Set commands queued")
    waiting.add_metric([], commands["waiting"])
    yield waiting


def families(stats: dict[str, Any]) -> Iterator[Metric]:
    """The bridge's own families from `Bridge.stats`."""
    yield from output_families(stats)
    for name, documentation, key in COUNTERS:
        counter = CounterMetricFamily(name, documentation)
        counter.add_metric([], stats[key])
        yield counter


class BridgeSource(PollerSource):
    """``pyrtu bridge``'s `pyrtu.metrics.server.Source`: its poller's metrics
    (`PollerSource`) and the bridge's own."""

    def __init__(self, bridge: Bridge, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(bridge.poller, loop)
        self.bridge = bridge

    def _snapshot(self) -> tuple[Any, dict[str, Any]]:
        return poller_snapshot(self.poller, self.latencies), self.bridge.stats()

    def collect(self) -> Iterator[Metric]:
        polled, stats = on_loop(self.loop, self._snapshot)
        yield from poller_families(polled, self.poller.config, self.limits)
        yield from families(stats)

    def health(self) -> list[str]:
        problems: list[str] = on_loop(self.loop, self.bridge.health)
        return problems


__all__ = ["BridgeSource", "families", "output_families"]
