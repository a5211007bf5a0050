"""``pyrtu bridge``'s metrics in Sparkplug B mode (a ``[sparkplug]`` table): the
edge node's poller's (`pyrtu.metrics.poller`), what it shares with the JSON
bridge under the same names (`pyrtu.metrics.bridge.output_families`: the broker
connection, the outbox's depth, size, oldest age and drops, task failures, the
set commands), and its own ``pyrtu_sparkplug_*`` families, read at each scrape
from `EdgeNode.stats` (its counters and state) on its event loop.

No secret reaches a label or a value: the MQTT user, password and TLS files are
never read here (`EdgeNode.stats` holds none), and the broker is named only in
``/healthz``'s reason (its URL cannot carry credentials: `pyrtu.bridge.config`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from .bridge import output_families
from .poller import PollerSource
from .poller import families as poller_families
from .poller import snapshot as poller_snapshot
from .server import on_loop

if TYPE_CHECKING:
    from pyrtu.sparkplug.node import EdgeNode

#: the message types the node counts (``type`` label) and their `EdgeNode.counts` key
MESSAGES = (("NBIRTH", "nbirth"), ("DBIRTH", "dbirth"), ("DDATA", "ddata"), ("DDEATH", "ddeath"))
#: the reasons a command is refused (``reason`` label; always exposed, 0 until one
#: happens): the node's own (a payload that is no Sparkplug B, a value of the
#: wrong type, a metric or device it does not have) and the set path's
REFUSALS = (
    "malformed",
    "validation",
    "unknown_metric",
    "unknown_device",
    "unknown_point",
    "not_writable",
    "busy",
)
#: (metric, help, `EdgeNode.counts` key) of the node's other counters
COUNTERS = (
    ("pyrtu_sparkplug_rebirths", "Rebirths the host asked for (NCMD Node Control/Rebirth)",
     "rebirths"),
    ("pyrtu_sparkplug_host_offline", "Times the primary host went offline while the node was "
     "born (NDEATH, disconnect, wait)", "host_offline"),
    ("pyrtu_sparkplug_unforwarded", "Outbox records passed by: their device dead when their "
     "turn came", "unforwarded"),
    ("pyrtu_sparkplug_foreign_records", "Outbox records passed by: no point update (an earlier "
     "pyrtu's JSON mode's)", "foreign_records"),
)  # fmt: skip


def shared(stats: dict[str, Any]) -> dict[str, Any]:
    """`EdgeNode.stats` keyed as `pyrtu.metrics.bridge.output_families` reads them:
    an update the outbox refused is a drop, as the JSON bridge counts it."""
    return {
        "connected": stats["connected"],
        "connections": stats["connects"],
        "outages": stats["outages"],
        "drops": stats["outbox_dropped"] + stats["refused"],
        "task_failures": stats["task_failures"],
        "outbox_depth": stats["outbox_depth"],
        "outbox_bytes": stats["outbox_bytes"],
        "oldest_unsent_s": stats["oldest_unsent_s"],
        "commands": stats["commands"],
    }


def families(stats: dict[str, Any], devices: list[str]) -> Iterator[Metric]:
    """The edge node's families from `EdgeNode.stats` (``devices``: every device's
    id, as configured)."""
    yield from output_families(shared(stats))
    info = GaugeMetricFamily(
        "pyrtu_sparkplug_node_info",
        "The Sparkplug edge node: its group and edge node ids",
        labels=["group_id", "edge_node_id"],
    )
    info.add_metric([stats["group_id"], stats["edge_node_id"]], 1)
    born = GaugeMetricFamily(
        "pyrtu_sparkplug_born",
        "1 while the node is born on the current connection (NBIRTH published), else 0",
    )
    born.add_metric([], 1 if stats["born"] else 0)
    bdseq = GaugeMetricFamily(
        "pyrtu_sparkplug_bdseq", "The bdSeq of the last CONNECT (its NBIRTH's and NDEATH's)"
    )
    bdseq.add_metric([], stats["bdseq"])
    alive = GaugeMetricFamily(
        "pyrtu_sparkplug_device_alive",
        "0 while the device is dead (its slave offline or its port down: a DDEATH), else 1",
        labels=["device"],
    )
    living = set(stats["devices_alive"])
    for device in devices:
        alive.add_metric([device], 1 if device in living else 0)
    yield from (info, born, bdseq, alive)
    messages = CounterMetricFamily(
        "pyrtu_sparkplug_messages",
        "Sparkplug messages the node published, by type (NDEATH aside: the will)",
        labels=["type"],
    )
    for kind, key in MESSAGES:
        messages.add_metric([kind], stats[key])
    published = CounterMetricFamily(
        "pyrtu_sparkplug_metrics_published",
        "Metric values published in DDATA: live, or historical (waited in the outbox)",
        labels=["kind"],
    )
    published.add_metric(["live"], stats["metrics_live"])
    published.add_metric(["historical"], stats["metrics_historical"])
    yield from (messages, published)
    for name, documentation, key in COUNTERS:
        counter = CounterMetricFamily(name, documentation)
        counter.add_metric([], stats[key])
        yield counter
    refused = CounterMetricFamily(
        "pyrtu_sparkplug_commands_refused",
        "NCMD and DCMD metrics refused (never written), by reason",
        labels=["reason"],
    )
    counts = stats["dcmd_refused"]
    for reason in (*REFUSALS, *sorted(set(counts) - set(REFUSALS))):
        refused.add_metric([reason], counts.get(reason, 0))
    yield refused


class SparkplugSource(PollerSource):
    """``pyrtu bridge``'s `pyrtu.metrics.server.Source` in Sparkplug mode: its
    poller's metrics (`PollerSource`) and the edge node's."""

    def __init__(self, node: EdgeNode, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(node.poller, loop)
        self.node = node
        self.devices = [device.id for device in node.spb.devices]

    def _snapshot(self) -> tuple[Any, dict[str, Any]]:
        return poller_snapshot(self.poller, self.latencies), self.node.stats()

    def collect(self) -> Iterator[Metric]:
        polled, stats = on_loop(self.loop, self._snapshot)
        yield from poller_families(polled, self.poller.config, self.limits)
        yield from families(stats, self.devices)

    def health(self) -> list[str]:
        problems: list[str] = on_loop(self.loop, self.node.health)
        return problems


__all__ = ["SparkplugSource", "families"]
