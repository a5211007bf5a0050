"""A poll block that answers exactly what it answered last time (most of a plant's
registers, most of the time): the scheduler says `Unchanged` for the block instead
of decoding an `Update` per point; the poller counts the values as read, moves
their age and their latest sample's time on, and delivers nothing when only
changes are delivered, every sample (decoded) when all are.  Decoding is a
function of the registers, so this changes no value anyone sees; the expected
values come from `struct`, not from the decoder."""

from __future__ import annotations

import asyncio
import struct
from typing import Any

import pytest

from pyrtu import DataStore
from pyrtu.poller import BusScheduler, Point, Poller, Update, Wire
from pyrtu.poller.config import Bus
from pyrtu.poller.events import Tracker, Unchanged
from pyrtu.tcp.server import TcpServer

WIRE = Wire(11 / 19200, 0.002005, 0.002005)


def pt(address: int, name: str, **kw: Any) -> Point:
    fields: dict[str, Any] = dict(bus="b", slave=1, table="holding", interval=1.0)
    fields.update(kw)
    return Point(name, address=address, **fields)


POINTS = [pt(0, "u"), pt(1, "i", type="int16"), pt(2, "f", type="float32")]
F32 = struct.unpack(">HH", struct.pack(">f", 21.5))  # the float's two registers, ABCD
REGS = [7, 0xFFFE, *F32]


def answer(sched: BusScheduler, data: list[int], now: float) -> list[Any]:
    req = sched.next_request(now)
    assert req is not None and req.kind == "poll" and (req.address, req.count) == (0, 4)
    return list(sched.on_response(req, data, now))


def test_the_same_registers_again_are_one_unchanged_for_the_block() -> None:
    sched = BusScheduler("b", POINTS, WIRE, stamp_offset=100.0)
    first = answer(sched, list(REGS), 0.0)
    assert [(e.point.name, e.value) for e in first if isinstance(e, Update)] == [
        ("u", 7), ("i", -2), ("f", 21.5)
    ]  # fmt: skip
    again = answer(sched, list(REGS), 1.0)  # an equal list, not the same object
    assert len(again) == 1 and isinstance(again[0], Unchanged)
    u = again[0]
    assert [p.name for p in u.points] == ["u", "i", "f"]
    assert u.time == 101.0 and u.address == 0 and list(u.data) == REGS
    # its samples, where every one is delivered: as decoded from the registers
    assert [(x.point.name, x.value, x.time) for x in u.updates()] == [
        ("u", 7, 101.0), ("i", -2, 101.0), ("f", 21.5, 101.0)
    ]  # fmt: skip


@pytest.mark.parametrize("index", range(len(REGS)))
def test_one_register_changed_is_decoded_again(index: int) -> None:
    sched = BusScheduler("b", POINTS, WIRE)
    answer(sched, list(REGS), 0.0)
    changed = list(REGS)
    changed[index] ^= 1  # the least change there is, in any register of the block
    events = answer(sched, changed, 1.0)
    assert [type(e) for e in events] == [Update] * 3
    # and the block's new registers are what "unchanged" is judged against from now
    again = answer(sched, list(changed), 2.0)
    assert [type(e) for e in again] == [Unchanged]
    back = answer(sched, list(REGS), 3.0)
    assert [type(e) for e in back] == [Update] * 3


def test_a_tracker_reread_moves_age_and_time_not_the_value() -> None:
    tracker = Tracker()
    p = POINTS[0]
    assert tracker.offer(Update(p, 7, 10.0), seen=5.0)
    tracker.reread([p], seen=6.5, stamp=11.5)
    assert tracker.age("u", 7.0) == pytest.approx(0.5)
    assert tracker.last("u") == Update(p, 7, 11.5)
    assert tracker.latest() == {"u": Update(p, 7, 11.5)}
    # nothing to deliver again; a change is delivered as before
    assert not tracker.offer(Update(p, 7, 12.0), seen=7.0)
    assert tracker.last("u") == Update(p, 7, 12.0)
    assert tracker.offer(Update(p, 8, 13.0), seen=8.0)
    # a reread older than the latest sample leaves the sample's own time
    tracker.reread([p], seen=8.5, stamp=12.5)
    assert tracker.last("u") == Update(p, 8, 13.0)
    tracker.reread([p], seen=9.0, stamp=13.0)  # (the same time: the same sample)
    assert tracker.last("u") == Update(p, 8, 13.0)


INTERVAL = 0.1


def _poll(changes_only: bool, seconds: float) -> tuple[list[Update], Poller]:
    """A poller of the three points over Modbus TCP (a pyrtu `TcpServer` whose
    registers never change), every `INTERVAL` for ``seconds``."""
    store = DataStore()
    store.holding_registers.add_range(0, list(REGS))

    async def main() -> tuple[list[Update], Poller]:
        server = TcpServer.for_store(1, store)
        await server.start("127.0.0.1", 0)
        assert server.address is not None
        try:
            bus = Bus("b", f"tcp://127.0.0.1:{server.address[1]}", master={"timeout": 1.0})
            points = [pt(p.address, p.name, type=p.type, interval=INTERVAL) for p in POINTS]
            poller = Poller(buses=[bus], points=points, changes_only=changes_only)
            got: list[Update] = []
            poller.on_update(got.append)
            await poller.run(seconds)
            return got, poller
        finally:
            await server.close()

    return asyncio.run(main())


@pytest.mark.wall_clock
def test_only_changes_delivered_an_unchanged_block_is_read_not_delivered() -> None:
    got, poller = _poll(True, 10 * INTERVAL)
    assert [(u.point.name, u.value) for u in got] == [("u", 7), ("i", -2), ("f", 21.5)]
    summary = poller.summary()
    reads = summary["values_read"] // 3
    assert reads >= 5 and summary["values_read"] == 3 * reads  # every read counted
    latest = poller.latest()
    # the latest sample's time is the last read's, not the first (delivered) one's:
    # at least the reads after the first, an interval apart, later
    assert latest["u"].value == 7
    assert latest["u"].time >= got[0].time + (reads - 1) * INTERVAL * 0.9
    age = poller.age("f")
    assert age is not None and age < 5 * INTERVAL


@pytest.mark.wall_clock
def test_every_sample_delivered_an_unchanged_block_is_delivered_decoded() -> None:
    got, poller = _poll(False, 10 * INTERVAL)
    reads = poller.summary()["values_read"] // 3
    assert reads >= 5 and len(got) == 3 * reads
    by_name: dict[str, set[object]] = {}
    for u in got:
        by_name.setdefault(u.point.name, set()).add(u.value)
    assert by_name == {"u": {7}, "i": {-2}, "f": {21.5}}
    times = sorted({u.time for u in got if u.point.name == "u"})
    assert len(times) == reads  # a sample per read, each with its own time


def test_an_unchanged_block_names_its_points_by_the_blocks_own_tuple() -> None:
    """Every `Unchanged` of a block carries the block's own tuple of points, the same
    object each time: the tracker keeps one group per block by it (`Tracker.reread`),
    so a thousand devices' rereads cost a lookup each and nothing accumulates."""
    sched = BusScheduler("b", POINTS, WIRE)
    answer(sched, list(REGS), 0.0)
    (a,) = answer(sched, list(REGS), 1.0)
    (b,) = answer(sched, list(REGS), 2.0)
    assert isinstance(a, Unchanged) and isinstance(b, Unchanged)
    assert type(a.points) is tuple and a.points is b.points
    assert a.points is sched.blocks[0].points
