"""parse_stream: the C core against the pure-Python twin on a 10 MB capture."""

from __future__ import annotations

from typing import Any

import pytest
from synth import mixed_traffic

import pyrtu

SIZE = 10_000_000


@pytest.fixture(scope="module")
def capture() -> bytes:
    return mixed_traffic(SIZE)


@pytest.mark.benchmark(group="parse_stream 10 MB")
@pytest.mark.parametrize("name", ["c", "python"])
def test_parse_stream(benchmark: Any, capture: bytes, name: str) -> None:
    mod = pyrtu.backend(name)
    rounds = 15 if name == "c" else 3
    result = benchmark.pedantic(mod.parse_stream, args=(capture,), rounds=rounds, iterations=1)
    benchmark.extra_info["bytes"] = len(capture)
    benchmark.extra_info["entries"] = len(result)
    assert result.counters["request"] > 100_000  # the capture really was parsed


@pytest.mark.benchmark(group="parse_stream 10 MB, chunk times")
def test_parse_stream_timed_c(benchmark: Any, capture: bytes) -> None:
    """With a timestamp every 64 bytes (a capture from the virtual bus)."""
    chunks = [(o, 1.0 + o * 1e-6) for o in range(0, len(capture), 64)]
    c = pyrtu.backend("c")
    result = benchmark.pedantic(
        c.parse_stream, args=(capture,), kwargs={"chunks": chunks, "baudrate": 115200}, rounds=5
    )
    benchmark.extra_info["bytes"] = len(capture)
    assert len(result) > 100_000


@pytest.mark.benchmark(group="framer 1 MB fed in 64-byte reads")
@pytest.mark.parametrize("name", ["c", "python"])
def test_framer_feed(benchmark: Any, capture: bytes, name: str) -> None:
    mod = pyrtu.backend(name)
    data = capture[:1_000_000]

    def run() -> int:
        f = mod.Framer("monitor", baudrate=115200)
        now = 1.0
        count = 0
        for pos in range(0, len(data), 64):
            f.receive_data(data[pos : pos + 64], now)
            now += 0.0001
            count += len(f.events())
        return count

    count = benchmark.pedantic(run, rounds=3 if name == "c" else 1, iterations=1)
    benchmark.extra_info["bytes"] = len(data)
    assert count > 10_000
