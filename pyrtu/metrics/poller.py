"""The poller's metrics (``pyrtu poll --config`` and, inside it, ``pyrtu bridge``).

Read at each scrape from the poller's own figures: `Poller.bus_summary` (per bus:
transactions, utilisation, load, port state and outages, task failures, values
read), `Poller.slave_stats` (per slave: requests, responses, timeouts, exception
responses, frame errors, state, wire time) and `Poller.latest` (when each point
was last read); nothing is counted twice.  The latency histograms are the one
thing observed per transaction (`Poller.on_latency`, `pyrtu.metrics.histogram`).

A point is *stale* when its value is not live: never read, its slave offline, its
bus's port down, or read longer ago than `stale_after` (three intervals, or one
interval and the bus's silence timer when that is longer).  A point the poller
dropped (exception 2 on its own: it cannot be read) is counted apart.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from pyrtu.poller import Poller
from pyrtu.poller.config import PollerConfig

from .histogram import Latencies
from .histogram import Snapshot as LatencySnapshot
from .histogram import family as histogram_family
from .server import on_loop

#: the kinds of ``pyrtu_poll_errors_total`` and the `SlaveStats` field of each
ERROR_KINDS = (("timeout", "timeouts"), ("exception", "exceptions"), ("frame", "frame_errors"))


def stale_after(config: PollerConfig) -> dict[str, float]:
    """Per point: the age (seconds) past which its value is stale."""
    silence = {
        b.name: float(b.master.get("timeout", 1.0)) * (1 + int(b.master.get("retries", 0)))
        for b in config.buses
    }
    return {p.name: max(3 * p.interval, p.interval + silence[p.bus]) for p in config.points}


@dataclass
class PollerSnapshot:
    """The poller's figures, copied on its loop's thread at one moment."""

    buses: list[dict[str, Any]]
    slaves: list[tuple[str, int, dict[str, int], bool | None, float]]
    read_at: dict[str, float]  # point -> when last read (time.time() clock)
    dropped: frozenset[str]
    latencies: LatencySnapshot
    now: float  # time.time() when copied


def snapshot(poller: Poller, latencies: Latencies) -> PollerSnapshot:
    """Copy the figures (run it on the poller's loop: `pyrtu.metrics.server.on_loop`)."""
    slaves = [
        (s.bus, s.slave, {field: getattr(s, field) for _, field in ERROR_KINDS}
         | {"requests": s.requests, "responses": s.responses}, s.online, s.busy)
        for s in poller.slave_stats()
    ]  # fmt: skip
    dropped = frozenset().union(*(poller.scheduler(b.name).dropped for b in poller.config.buses))
    return PollerSnapshot(
        poller.bus_summary(),
        slaves,
        {name: update.time for name, update in poller.latest().items()},
        dropped,
        latencies.snapshot(),
        time.time(),
    )


def families(
    snap: PollerSnapshot, config: PollerConfig, limits: dict[str, float]
) -> Iterator[Metric]:
    """The poller's metric families from a snapshot (on any thread)."""
    bus_labels = ["bus"]
    transactions = CounterMetricFamily(
        "pyrtu_poll_transactions",
        "Transactions ended on the bus (answered or not)",
        labels=bus_labels,
    )
    values = CounterMetricFamily(
        "pyrtu_poll_values_read", "Point values read on the bus", labels=bus_labels
    )
    busy = CounterMetricFamily(
        "pyrtu_poll_bus_busy_seconds",
        "Wire time of the bus's transactions (rate() of it: the recent utilisation)",
        labels=bus_labels,
    )
    utilisation = GaugeMetricFamily(
        "pyrtu_poll_bus_utilisation_ratio",
        "Wire-busy time over wall time since the poller started (0..1)",
        labels=bus_labels,
    )
    load = GaugeMetricFamily(
        "pyrtu_poll_bus_load_ratio",
        "Wire time the configured rates ask for per second (above 1: more than the wire carries)",
        labels=bus_labels,
    )
    port_up = GaugeMetricFamily(
        "pyrtu_poll_port_up",
        "0 while the bus's port is down (an outage: retried with back-off), else 1",
        labels=["bus", "port"],
    )
    outages = CounterMetricFamily(
        "pyrtu_poll_port_outages", "Outages of the bus's port", labels=bus_labels
    )
    task_failures = CounterMetricFamily(
        "pyrtu_poll_task_failures",
        "Times the bus's task raised (each restarted on the back-off)",
        labels=bus_labels,
    )
    busy_by_bus: dict[str, float] = {}
    for _bus, _slave, _counts, _online, seconds in snap.slaves:
        busy_by_bus[_bus] = busy_by_bus.get(_bus, 0.0) + seconds
    down = set()
    for doc in snap.buses:
        this = [doc["bus"]]
        transactions.add_metric(this, doc["transactions"])
        values.add_metric(this, doc["values_read"])
        busy.add_metric(this, busy_by_bus.get(doc["bus"], 0.0))
        utilisation.add_metric(this, doc["utilisation"])
        load.add_metric(this, doc["load"])
        port_up.add_metric([doc["bus"], doc["port"]], 0 if doc["port_state"] == "down" else 1)
        outages.add_metric(this, doc["outages"])
        task_failures.add_metric(this, doc["task_failures"])
        if doc["port_state"] == "down":
            down.add(doc["bus"])
    yield from (transactions, values, busy, utilisation, load, port_up, outages, task_failures)

    slave_labels = ["bus", "slave"]
    requests = CounterMetricFamily(
        "pyrtu_poll_requests", "Transactions addressed to the slave", labels=slave_labels
    )
    responses = CounterMetricFamily(
        "pyrtu_poll_responses", "Normal responses of the slave", labels=slave_labels
    )
    errors = CounterMetricFamily(
        "pyrtu_poll_errors",
        "Failed transactions by kind: timeout (no answer), exception (an exception "
        "response), frame (a garbled answer)",
        labels=["bus", "slave", "kind"],
    )
    online = GaugeMetricFamily(
        "pyrtu_poll_slave_online",
        "1 while the slave answers, 0 when offline or not answered yet",
        labels=slave_labels,
    )
    offline = set()
    for bus, slave, counts, state, _seconds in snap.slaves:
        labels = [bus, str(slave)]
        requests.add_metric(labels, counts["requests"])
        responses.add_metric(labels, counts["responses"])
        for kind, field in ERROR_KINDS:
            errors.add_metric([*labels, kind], counts[field])
        online.add_metric(labels, 1 if state else 0)
        if state is False:
            offline.add((bus, slave))
    yield from (requests, responses, errors, online)
    yield histogram_family(
        "pyrtu_poll_latency_seconds",
        "Time from a request to its answer (responses and exception responses)",
        snap.latencies,
    )

    total: dict[str, int] = {b.name: 0 for b in config.buses}
    stale: dict[str, int] = dict(total)
    dropped: dict[str, int] = dict(total)
    for p in config.points:
        total[p.bus] += 1
        if p.name in snap.dropped:
            dropped[p.bus] += 1
            continue
        read_at = snap.read_at.get(p.name)
        if (
            read_at is None
            or p.bus in down
            or (p.bus, p.slave) in offline
            or snap.now - read_at > limits[p.name]
        ):
            stale[p.bus] += 1
    for name, documentation, counts in (
        ("pyrtu_poll_points", "Points configured on the bus", total),
        (
            "pyrtu_poll_points_stale",
            "Points whose value is not live: never read, slave offline, port down, "
            "or older than three intervals",
            stale,
        ),
        ("pyrtu_poll_points_dropped", "Points dropped (they cannot be read: exception 2)", dropped),
    ):
        gauge = GaugeMetricFamily(name, documentation, labels=bus_labels)
        for bus, count in counts.items():
            gauge.add_metric([bus], count)
        yield gauge


class PollerSource:
    """``pyrtu poll --config``'s `pyrtu.metrics.server.Source`."""

    def __init__(self, poller: Poller, loop: asyncio.AbstractEventLoop) -> None:
        self.poller = poller
        self.loop = loop
        self.latencies = Latencies()
        self.limits = stale_after(poller.config)
        poller.on_latency(self.latencies.observe)

    def collect(self) -> Iterator[Metric]:
        snap = on_loop(self.loop, lambda: snapshot(self.poller, self.latencies))
        yield from families(snap, self.poller.config, self.limits)

    def health(self) -> list[str]:
        problems: list[str] = on_loop(self.loop, self.poller.health)
        return problems


__all__ = ["PollerSnapshot", "PollerSource", "families", "snapshot", "stale_after"]
