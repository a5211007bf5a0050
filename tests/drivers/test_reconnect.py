"""The shared retry schedule (pyrtu.drivers.reconnect): report once, back off, recover."""

from __future__ import annotations

import random

import pytest

from pyrtu.drivers.reconnect import Backoff, Reconnect


def test_first_failure_is_reported_once_and_waits_grow_to_the_maximum() -> None:
    r = Reconnect(Backoff(initial=0.5, maximum=4.0, jitter=0.0))
    assert not r.down and r.due(0.0) and r.wait(0.0) == 0.0
    assert r.failed(10.0, OSError("gone")) is True
    waits = [r.retry_at - 10.0]  # type: ignore[operator]
    for _ in range(6):
        assert r.failed(10.0, "still gone") is False
        waits.append(r.retry_at - 10.0)  # type: ignore[operator]
    assert waits == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0, 4.0]
    assert r.down and r.outages == 1 and r.outage is not None and r.outage.attempts == 7
    assert not r.due(13.9) and r.due(14.0) and r.wait(12.0) == pytest.approx(2.0)
    o = r.recovered(20.0)
    assert o is not None and o.since == 10.0 and o.duration == 10.0 and o.error == "still gone"
    assert not r.down and r.retry_at is None and r.recovered(21.0) is None
    assert r.failed(30.0, OSError()) is True and r.outage.error == "OSError"  # type: ignore[union-attr]
    assert r.outages == 2 and r.retry_at == 30.5


def test_jitter_spreads_waits_within_bounds() -> None:
    b = Backoff(initial=1.0, maximum=8.0, jitter=0.2)
    rng = random.Random(7)
    ds = [b.delay(3, rng) for _ in range(200)]
    assert all(3.2 <= d <= 4.8 for d in ds) and len(set(ds)) > 100
    assert all(b.delay(10, rng) <= 8.0 for _ in range(50))


@pytest.mark.parametrize(
    ("kw", "exc", "word"),
    [
        ({"initial": 0}, ValueError, "initial"),
        ({"initial": True}, TypeError, "initial"),
        ({"maximum": float("inf")}, ValueError, "maximum"),
        ({"initial": 5.0, "maximum": 1.0}, ValueError, "maximum"),
        ({"factor": 0.5}, ValueError, "factor"),
        ({"factor": "2"}, TypeError, "factor"),
        ({"jitter": 1.0}, ValueError, "jitter"),
        ({"jitter": None}, TypeError, "jitter"),
    ],
)
def test_bad_backoff_names_the_argument(kw: dict[str, object], exc: type, word: str) -> None:
    with pytest.raises(exc, match=word):
        Backoff(**kw)  # type: ignore[arg-type]
