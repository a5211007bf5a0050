"""How the user's benchmark suite times a call: repeated in batches for a budget of
seconds, the median of the batches' time per call (the figure the developers'
pytest-benchmark runs report too), with the spread between batches."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class CallTiming:
    """``median`` and ``low``/``high`` (the fastest and slowest batch) in seconds per
    call, over ``batches`` batches of ``per_batch`` calls."""

    median: float
    low: float
    high: float
    batches: int
    per_batch: int


def time_call(fn: Callable[[], object], budget: float, *, min_batches: int = 5) -> CallTiming:
    """Time ``fn()``: batches sized to last about ``budget / 20`` seconds each, until
    ``budget`` seconds have passed and at least ``min_batches`` batches ran."""
    if budget <= 0:
        raise ValueError(f"budget must be > 0 seconds, not {budget!r}")
    clock = time.perf_counter
    n = 1
    while True:  # calibrate: a batch of about budget/20
        t0 = clock()
        for _ in range(n):
            fn()
        took = clock() - t0
        if took >= budget / 20 or n >= 1 << 24:
            break
        n = n * 2 if took <= 0 else max(n * 2, int(n * (budget / 20) / took))
    per_call: list[float] = [took / n]
    start = clock()
    while clock() - start < budget or len(per_call) < min_batches:
        t0 = clock()
        for _ in range(n):
            fn()
        per_call.append((clock() - t0) / n)
    return CallTiming(statistics.median(per_call), min(per_call), max(per_call), len(per_call), n)


def percentile(values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1) of ``values``, nearest rank (a value that occurred)."""
    if not values:
        raise ValueError("percentile of no values")
    if not 0 <= q <= 1:
        raise ValueError(f"q must be within 0..1, not {q!r}")
    ordered = sorted(values)
    rank = max(1, math.ceil(q * len(ordered)))  # 1-based: the smallest with q of them at or below
    return ordered[rank - 1]


__all__ = ["CallTiming", "percentile", "time_call"]
