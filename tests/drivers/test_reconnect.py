"""The shared retry schedule (pyrtu.drivers.reconnect): report once, back off, recover;
and a master's link on it (`LinkRevival`)."""

from __future__ import annotations

import logging
import random

import pytest

from pyrtu.drivers.links import LinkRevival
from pyrtu.drivers.reconnect import Backoff, Reconnect
from pyrtu.pdu.errors import PortError


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


def test_a_link_revival_says_when_the_next_attempt_is_and_logs_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """`LinkRevival`, a master's link on that schedule: the first attempt at once, then
    none until it is due (a `PortError` saying when), one warning per outage, one info
    when it ends; in a TCP link's words by default, a serial port's when asked."""
    caplog.set_level(logging.INFO, logger="pyrtu.drivers.master")
    attempts: list[str] = []

    def fails() -> None:
        attempts.append("fails")
        raise PortError("/dev/ttyUSB0", "cannot open: gone")

    revival = LinkRevival(
        "/dev/ttyUSB0",
        Backoff(initial=60.0, maximum=60.0, jitter=0.0),
        verb="reopen",
        down="not open",
    )
    with pytest.raises(PortError, match="cannot open: gone"):
        revival.attempt(fails)
    for _ in range(2):
        with pytest.raises(
            PortError,
            match=r"^/dev/ttyUSB0: not open \(/dev/ttyUSB0: cannot open: gone\); "
            r"the next attempt in (59|60)\.\d\d s$",
        ):
            revival.attempt(fails)
    assert attempts == ["fails"]
    revival.reconnect._retry_at = 0.0  # due
    revival.attempt(lambda: attempts.append("works"))
    assert attempts == ["fails", "works"] and not revival.reconnect.down
    logged = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert logged == [
        (logging.WARNING, "/dev/ttyUSB0: cannot open: gone; reopening on the back-off"),
        (logging.INFO, "/dev/ttyUSB0: reopened after 1 failed attempts"),
    ]
    revival.closed = True
    with pytest.raises(PortError, match="the master is closed"):
        revival.attempt(lambda: attempts.append("closed"))
    tcp = LinkRevival("tcp://h:502", Backoff(initial=60.0, maximum=60.0, jitter=0.0))
    with pytest.raises(PortError):
        tcp.attempt(fails)
    with pytest.raises(PortError, match=r"^tcp://h:502: not connected \(.*\); the next attempt in"):
        tcp.attempt(fails)
    assert "reconnecting on the back-off" in caplog.records[-1].getMessage()
