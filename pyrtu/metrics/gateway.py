"""``pyrtu gateway``'s metrics, read at each scrape from `Gateway.stats` (its
counters, open connections, per-bus queues, transactions, wire time and state),
and the latency histograms the bus workers observe (`Gateway.on_latency`).

The same families serve ``pyrtu simulate --tcp`` (its `TcpServer` is a gateway
with the drive in place of a bus): `counter_families` with another prefix.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator, Mapping
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from pyrtu.gateway import Gateway
from pyrtu.security.policy import REFUSAL_KINDS

from .histogram import Latencies
from .histogram import family as histogram_family
from .server import on_loop

#: (counter of `Gateway.stats`, ``kind`` label) of the answers the gateway gives
#: itself: no answer from the device (0x0B), busy (0x06), no route (0x0A), the
#: bus down (0x0A)
REQUEST_ERRORS = (
    ("timeouts", "timeout"),
    ("busy", "busy"),
    ("no_route", "no_route"),
    ("bus_unavailable", "bus_unavailable"),
)
#: (counter, ``kind`` label) of the connections closed or refused by the gateway (and
#: the UDP listener's datagrams dropped for not being one Modbus ADU)
CONNECTION_ERRORS = (
    ("refused", "refused"),
    ("evicted", "evicted"),
    ("bad_headers", "bad_header"),
    ("slow_clients", "slow_client"),
    ("header_timeouts", "header_timeout"),
    ("idle_timeouts", "idle_timeout"),
    ("tls_failures", "tls_handshake"),
    ("bad_datagrams", "bad_datagram"),
)


def counter_families(prefix: str, stats: Mapping[str, Any]) -> Iterator[Metric]:
    """The families of a gateway's counters and connections (``prefix``:
    ``pyrtu_gateway`` or ``pyrtu_simulate_tcp``)."""
    for key, documentation in (
        ("requests", "Requests received (every unit id)"),
        ("answers", "Normal answers sent"),
        ("exceptions", "Exception answers sent (the device's and the gateway's own)"),
        ("broadcasts", "Broadcasts (unit 0) sent to the buses"),
        ("connections", "TCP connections accepted"),
        ("answers_dropped", "Answers dropped: their client had gone"),
        ("task_failures", "Times a background task raised (each restarted on the back-off)"),
        ("audited_writes", "Executed writes recorded in the audit trail (--audit)"),
        ("audit_failures", "Executed writes the audit trail could not record"),
    ):
        counter = CounterMetricFamily(f"{prefix}_{key}", documentation)
        counter.add_metric([], stats[key])
        yield counter
    errors = CounterMetricFamily(
        f"{prefix}_errors",
        "Requests the gateway answered itself, by kind: timeout (0x0B), busy (0x06), "
        "no_route and bus_unavailable (0x0A)",
        labels=["kind"],
    )
    for key, kind in REQUEST_ERRORS:
        errors.add_metric([kind], stats[key])
    yield errors
    denied = CounterMetricFamily(
        f"{prefix}_denied",
        "Requests refused by the access policy (answered exception 01), by reason",
        labels=["reason"],
    )
    by_kind = stats.get("denied_by", {})
    for kind in (*REFUSAL_KINDS, *sorted(set(by_kind) - set(REFUSAL_KINDS))):
        denied.add_metric([kind], by_kind.get(kind, 0))
    yield denied
    closed = CounterMetricFamily(
        f"{prefix}_connection_errors",
        "Connections refused or closed by the gateway, by kind",
        labels=["kind"],
    )
    for key, kind in CONNECTION_ERRORS:
        closed.add_metric([kind], stats[key])
    yield closed
    clients = GaugeMetricFamily(f"{prefix}_clients_connected", "TCP clients connected now")
    clients.add_metric([], stats["open_connections"])
    unsent = GaugeMetricFamily(
        f"{prefix}_unsent_bytes", "Answers written and not yet taken by their clients (bytes)"
    )
    unsent.add_metric([], stats["unsent_bytes"])
    yield from (clients, unsent)


def bus_families(names: list[str], stats: Mapping[str, Any], seconds: float) -> Iterator[Metric]:
    """The per-bus families of `Gateway.stats` (``seconds``: since the start)."""
    labels = ["bus"]
    transactions = CounterMetricFamily(
        "pyrtu_gateway_bus_transactions", "Transactions the bus carried", labels=labels
    )
    busy = CounterMetricFamily(
        "pyrtu_gateway_bus_busy_seconds",
        "Time the bus spent in transactions (rate() of it: the recent utilisation)",
        labels=labels,
    )
    utilisation = GaugeMetricFamily(
        "pyrtu_gateway_bus_utilisation_ratio",
        "Time in transactions over wall time since the gateway started (0..1)",
        labels=labels,
    )
    queued = GaugeMetricFamily(
        "pyrtu_gateway_bus_queue_depth", "Requests waiting for the bus", labels=labels
    )
    up = GaugeMetricFamily(
        "pyrtu_gateway_bus_up", "0 while the bus's port is down (retried), else 1", labels=labels
    )
    outages = CounterMetricFamily(
        "pyrtu_gateway_bus_outages", "Outages of the bus's port", labels=labels
    )
    for i, name in enumerate(names):
        busy_seconds = stats["bus_busy_seconds"][i]
        transactions.add_metric([name], stats["bus_transactions"][i])
        busy.add_metric([name], busy_seconds)
        utilisation.add_metric([name], min(1.0, busy_seconds / seconds) if seconds > 0 else 0.0)
        queued.add_metric([name], stats["queued"][i])
        up.add_metric([name], 0 if stats["bus_down"][i] else 1)
        outages.add_metric([name], stats["bus_outages"][i])
    yield from (transactions, busy, utilisation, queued, up, outages)


class GatewaySource:
    """``pyrtu gateway``'s `pyrtu.metrics.server.Source`."""

    def __init__(self, gateway: Gateway, loop: asyncio.AbstractEventLoop) -> None:
        self.gateway = gateway
        self.loop = loop
        self.latencies = Latencies()
        self.started = time.monotonic()
        gateway.on_latency = self.latencies.observe

    def _snapshot(self) -> tuple[dict[str, Any], Any]:
        return self.gateway.stats(), self.latencies.snapshot()

    def collect(self) -> Iterator[Metric]:
        stats, latencies = on_loop(self.loop, self._snapshot)
        yield from counter_families("pyrtu_gateway", stats)
        yield from bus_families(self.gateway.bus_names(), stats, time.monotonic() - self.started)
        yield histogram_family(
            "pyrtu_gateway_latency_seconds",
            "Time a bus took to answer a request (responses and exception responses)",
            latencies,
        )

    def health(self) -> list[str]:
        problems: list[str] = on_loop(self.loop, self.gateway.health)
        return problems


__all__ = ["GatewaySource", "bus_families", "counter_families"]
