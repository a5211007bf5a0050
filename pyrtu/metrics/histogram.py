"""Latency histograms per bus and slave, observed where a transaction completes.

`Latencies.observe` is the one thing that runs per transaction: a dictionary
look-up, a bisection over the bucket bounds and three additions, on the thread of
the command's event loop (no lock: `snapshot` runs on that thread too, through
`pyrtu.metrics.server.on_loop`).  The exposition (`family`) is built from the
snapshot on the HTTP server's thread.
"""

from __future__ import annotations

from bisect import bisect_left

from prometheus_client.core import HistogramMetricFamily

#: the upper bounds of the buckets (seconds): a Modbus TCP answer on a LAN (a few
#: hundred microseconds) up to a slow serial device's timeout; +Inf is added
BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)

#: (bus, slave) -> (counts per bucket, the last one +Inf; sum of the seconds observed)
Snapshot = dict[tuple[str, int], tuple[list[int], float]]


class _Series:
    __slots__ = ("counts", "total")

    def __init__(self) -> None:
        self.counts = [0] * (len(BUCKETS) + 1)
        self.total = 0.0


class Latencies:
    """The latencies of the transactions of every (bus, slave) pair."""

    def __init__(self) -> None:
        self._series: dict[tuple[str, int], _Series] = {}

    def observe(self, bus: str, slave: int, seconds: float) -> None:
        """One transaction of ``slave`` on ``bus`` took ``seconds``."""
        key = (bus, slave)
        series = self._series.get(key)
        if series is None:
            series = self._series[key] = _Series()
        # Prometheus buckets are "less than or equal": the first bound >= seconds
        series.counts[bisect_left(BUCKETS, seconds)] += 1
        series.total += seconds

    def snapshot(self) -> Snapshot:
        """A copy of the counts (on the thread that observes)."""
        return {key: (list(s.counts), s.total) for key, s in self._series.items()}


def family(name: str, documentation: str, snapshot: Snapshot) -> HistogramMetricFamily:
    """The histogram ``name`` with labels bus and slave, cumulative buckets."""
    metric = HistogramMetricFamily(name, documentation, labels=["bus", "slave"])
    bounds = [*(repr(b) for b in BUCKETS), "+Inf"]
    for (bus, slave), (counts, total) in sorted(snapshot.items()):
        running = 0
        buckets: list[tuple[str, float]] = []
        for bound, count in zip(bounds, counts, strict=True):
            running += count
            buckets.append((bound, running))
        metric.add_metric([bus, str(slave)], buckets, total)
    return metric


__all__ = ["BUCKETS", "Latencies", "Snapshot", "family"]
