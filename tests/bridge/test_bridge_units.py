"""The bridge's pure parts on a fake clock: report by exception with qualities,
command parsing and checks, the rate limit, the acknowledgement window, payloads."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from pyrtu.bridge.commands import CommandQueue, Refusal, TokenBucket, check_value, parse, result
from pyrtu.bridge.delivery import DeliveryWindow
from pyrtu.bridge.topics import body, payload, split_record
from pyrtu.outbox.report import Reporter
from pyrtu.poller import Point

SPEED = Point("d.speed", "line", 1, "holding", 2, scale=0.1, deadband=0.5)
STATUS = Point("d.status", "line", 1, "holding", 680)
OTHER = Point("e.status", "line", 2, "holding", 680)
REF = Point("d.ref", "line", 1, "holding", 683, type="int16")
FLAG = Point("d.flag", "line", 1, "coils", 0)
NAME = Point("d.name", "line", 1, "holding", 900, type="string", count=2)


def test_report_by_exception_deadband_and_max_age() -> None:
    r = Reporter([SPEED, STATUS], {"d.status": 10.0})
    assert r.update(SPEED, 30.0, 100.0, now=0.0)  # the first
    assert not r.update(SPEED, 30.4, 100.1, now=0.1)  # within the deadband
    assert r.update(SPEED, 30.6, 100.2, now=0.2)  # beyond it
    assert not r.update(SPEED, 30.6, 200.0, now=100.0)  # no max_age: never again
    assert r.update(STATUS, 5, 100.0, now=0.0)
    assert not r.update(STATUS, 5, 105.0, now=5.0)
    assert r.update(STATUS, 5, 110.0, now=10.0)  # max_age reached: again, unchanged
    assert not r.update(STATUS, 5, 111.0, now=11.0)
    # a write's read-back: any change, whatever the deadband, but never twice the same
    assert not r.update(STATUS, 5, 112.0, now=12.0, exact=True)  # a poll published it
    assert r.update(STATUS, 6, 112.5, now=12.5, exact=True)
    assert r.update(SPEED, 30.7, 200.1, now=100.1, exact=True)  # within the deadband
    assert not r.update(SPEED, 30.7, 200.2, now=100.2, exact=True)


def test_an_offline_slave_makes_its_points_stale_then_good_again() -> None:
    r = Reporter([SPEED, STATUS, OTHER], {})
    r.update(SPEED, 30.0, 100.0, 0.0)
    r.update(OTHER, 1, 100.0, 0.0)
    stale = r.slave_state("line", 1, False, now=1.0)
    # every point of slave 1, with the last value read and when (None: never read)
    assert stale == [(SPEED, 30.0, 100.0, "stale"), (STATUS, None, None, "stale")]
    assert r.quality("e.status") == "good"
    assert r.slave_state("line", 1, True, now=2.0) == []
    # the same value as before is published again: its quality changed
    assert r.update(SPEED, 30.0, 103.0, 3.0)
    assert r.quality("d.speed") == "good"
    assert r.dropped(STATUS, 104.0, 4.0) == (STATUS, None, 104.0, "bad")
    # a bad point stays bad when its slave goes offline (it was never live)
    assert r.slave_state("line", 1, False, 5.0) == [(SPEED, 30.0, 103.0, "stale")]


def test_a_bus_down_makes_every_point_of_the_bus_stale_once() -> None:
    far = Point("f.status", "other", 1, "holding", 680)
    r = Reporter([SPEED, STATUS, OTHER, far], {})
    for p in (SPEED, OTHER, far):
        r.update(p, 1, 100.0, 0.0)
    r.dropped(STATUS, 101.0, 1.0)
    # every point of the bus "line" (both slaves), the bad one left bad
    assert r.bus_down("line", 2.0) == [(SPEED, 1, 100.0, "stale"), (OTHER, 1, 100.0, "stale")]
    assert r.quality("f.status") == "good"  # another bus
    # already stale: not published stale again (a slave offline during the outage)
    assert r.slave_state("line", 1, False, 3.0) == [] and r.bus_down("line", 3.0) == []
    # back: the next read of each point is published as good, unchanged or not
    assert r.update(SPEED, 1, 104.0, 4.0) and r.quality("d.speed") == "good"


def test_payloads_and_records() -> None:
    part = body(SPEED, 30.5, 1700000000.25, "good")
    doc = json.loads(payload(part, 42, False))
    assert doc == {"value": 30.5, "time": 1700000000.25, "quality": "good", "seq": 42}
    assert json.loads(payload(part, 42, True))["historical"] is True
    never = json.loads(payload(body(SPEED, None, None, "stale"), 3, False))
    assert never == {"value": None, "time": None, "quality": "stale", "seq": 3}
    for v in (None, float("nan"), True, 7, 'text "q"', -1.5e-7):
        d = json.loads(payload(body(SPEED, v, 1.0, "stale"), 1, False))
        want = None if v is None or v != v else v
        assert d["value"] == want and d["quality"] == "stale"
    # a record of an earlier pyrtu: the topic, a newline, the body
    assert split_record(b"p/e/line/1/d.speed\n" + part) == ("p/e/line/1/d.speed", part)


@pytest.mark.parametrize(
    ("text", "retained", "want"),
    [
        (b"12.5", False, (12.5, None, None)),
        (b'{"value": true, "id": "x", "time": 5}', False, (True, "x", 5.0)),
        (b'{"value": 1, "id": 17}', False, (1, "17", None)),
        (b'{"id": "x"}', False, Refusal("malformed", 'no "value"', "x")),
        (b"\xff", False, "malformed"),
        (b"Infinity", False, "malformed"),
        (b'{"value": 1, "time": "now"}', False, "malformed"),
        (b'{"value": 1, "id": [1]}', False, "malformed"),
        (b"1", True, "retained"),
        (b"1" * 100, False, "too_large"),
        (b"", True, None),  # a retained command cleared: no command, no answer
        (b"", False, None),  # the same, delivered to a subscriber already there
    ],
)
def test_parse(text: bytes, retained: bool, want: object) -> None:
    got = parse(text, max_payload=64, retained=retained)
    if isinstance(want, str):
        assert isinstance(got, Refusal) and got.error == want
    else:
        assert got == want


def test_values_are_checked_before_anything_is_sent() -> None:
    ref = replace(REF, writable=True, min=-100, max=100)
    speed = replace(SPEED, writable=True, min=-100, max=100)
    assert check_value(ref, 50).value == 50
    assert check_value(FLAG, 1).value is True
    assert check_value(NAME, "ab").value == "ab"
    # an unscaled integer register holds whole numbers: refused, never rounded
    for v in (1.5, 0.5, -0.5, 2.000001):
        with pytest.raises(ValueError, match="not a whole number"):
            check_value(ref, v)
    assert check_value(ref, 2.0).value == 2 and not check_value(ref, 2.0).rounded
    # a scaled one rounds to its resolution (0.1), half away from zero, and says so
    assert not check_value(speed, 21.4).rounded and check_value(speed, 21.4).value == 21.4
    got = check_value(speed, 21.43)
    assert got.rounded and got.value == 21.4 and got.words == [214]
    assert check_value(speed, 21.45).words == [215]
    assert check_value(speed, 0.05).words == [1]
    with pytest.raises(ValueError, match="above the point's max"):
        check_value(ref, 101)
    with pytest.raises(ValueError, match="must be a number"):
        check_value(ref, "5")
    with pytest.raises(ValueError, match="true or false"):
        check_value(FLAG, 2)
    with pytest.raises(ValueError, match="at most 4 characters"):
        check_value(NAME, "abcde")
    with pytest.raises(ValueError, match="outside"):  # the register's range, scale undone
        check_value(SPEED, 7000.0)


def test_token_bucket_and_queue_bounds() -> None:
    b = TokenBucket(rate=2.0, burst=2.0, now=0.0)
    assert b.wait(0.0) == 0 and b.wait(0.0) == 0
    assert b.wait(0.0) == pytest.approx(0.5)
    assert b.wait(0.5) == 0
    q = CommandQueue(size=2, rate=1.0)
    from pyrtu.bridge.commands import SetCommand

    cmds = [SetCommand(REF, i, f"id{i}", 10.0, 0.0, "r") for i in range(3)]
    assert q.push(cmds[0]) and q.push(cmds[1]) and not q.push(cmds[2])
    assert q.refused == 1 and q.waiting == 2
    assert q.known("id0") == (True, None)
    q.done("id0", b"res")
    assert q.known("id0") == (True, b"res") and q.duplicates == 2
    assert q.pop(("line", 1)) is cmds[0] and q.waiting == 1
    assert json.loads(result("p", False, error="busy", message="m")) == {
        "ok": False,
        "point": "p",
        "error": "busy",
        "message": "m",
    }


def test_window_acknowledges_contiguously() -> None:
    w = DeliveryWindow(3)
    w.sent(10, mid=1, read_at=100.0)
    w.sent(11, mid=2, read_at=100.0)
    w.sent(12, mid=3, read_at=0.0)
    assert w.full
    assert not w.acked(2, 100.002)  # 10 still waits
    assert w.contiguous is None
    assert w.acked(1, 100.004) and w.contiguous == 11
    assert not w.acked(99, 1.0)  # a status or result, not a record
    assert w.acked(3, 1.0) and w.contiguous == 12 and len(w) == 0
    assert w.latency(50) == pytest.approx(0.002)
    w.sent(13, 4, 0.0)
    w.reset()
    assert len(w) == 0 and not w.acked(4, 1.0)


def test_memory_stays_bounded_whatever_the_backlog(tmp_path: object) -> None:
    """50 000 updates while no broker is reachable: the backlog is on disk; the
    process keeps a fixed window of recent records (under 3 MB here, where the
    backlog in memory would take 12 MB)."""
    import asyncio
    import time
    import tracemalloc
    from pathlib import Path

    from pyrtu.bridge import MqttConfig, make_bridge_config
    from pyrtu.bridge.bridge import Bridge
    from pyrtu.drivers.aio import run as aio_run
    from pyrtu.poller import Bus, Update, make_config

    pts = [Point(f"p{i}", "line", 1, "holding", i) for i in range(100)]
    poller = make_config([Bus("line", "/dev/null-never-opened")], pts)
    mqtt = MqttConfig("mqtt://127.0.0.1:1", edge="e", outbox=str(Path(str(tmp_path)) / "ob"))
    bridge = Bridge(make_bridge_config(poller, mqtt))

    async def main() -> tuple[int, int]:
        await bridge.start(poll=False)
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        for i in range(50_000):
            bridge.feed(Update(pts[i % 100], i, time.time()))
            if i % 5000 == 0:
                await asyncio.sleep(0)
        grown = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.stop()
        depth = bridge.stats()["outbox_depth"]
        await bridge.stop(drain=0)
        return grown, depth

    grown, depth = aio_run(main())
    assert depth == 50_000
    assert grown < 3_000_000, grown
