"""The poller end to end on the virtual bus with the simulated drives: values
decoded as the drives hold them, a write ahead of the polls, a slave unplugged and
replugged (offline and online events, the others unaffected), noise on the line,
a configuration whose rates exceed the wire, the sync facade."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import Counter
from collections.abc import Callable, Iterator

import pytest
from waiting import wait_for

from pyrtu.devices import CFW701Simulator, CV100Simulator, DriveSimulator, cv100, weg
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.poller import (
    Bus,
    Overload,
    Point,
    PointDropped,
    Poller,
    PortState,
    SlaveState,
    Update,
    make_config,
    profile_points,
)
from pyrtu.poller.events import Event

vbus = pytest.importorskip("pyrtu.vbus")
VirtualBus = vbus.VirtualBus
Faults = vbus.Faults

BAUD = 115200
#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


@contextlib.contextmanager
def drives(
    baud: int = BAUD, faults: object = None
) -> Iterator[tuple[object, list[DriveSimulator]]]:
    """Drop 0: the poller; drop 1: a CFW701 at 1; drop 2: a CV100 at 5."""
    with VirtualBus(3, baudrate=baud, parity="N", faults=faults) as bus:
        sims: list[DriveSimulator] = [CFW701Simulator(), CV100Simulator()]
        for drop, (sim, addr) in enumerate(zip(sims, (1, 5), strict=True), start=1):
            sim.serve(bus.paths[drop], addr, baudrate=baud, parity="N")
        try:
            yield bus, sims
        finally:
            for sim in sims:
                sim.close()


def config(bus_path: str, baud: int = BAUD, interval: float = 0.05, **bus_kw: object) -> object:
    points = profile_points("cfw701", "weg", "line", 1, interval)
    points += profile_points("cv100", "cv", "line", 5, interval)
    points.append(Point("weg.missing", "line", 1, "holding", 2900, interval=interval))
    points.append(Point("weg.ref", "line", 1, "holding", weg.P_REFERENCE, scale=0.5, interval=1))
    kw: dict[str, object] = dict(share=0.05, offline_after=2, backoff=0.1, max_backoff=0.4)
    kw.update(bus_kw)
    bus = Bus("line", bus_path, {"baudrate": baud, "parity": "N", "timeout": 0.2}, **kw)  # type: ignore[arg-type]
    return make_config([bus], points)


@pytest.mark.parametrize("master", ["aio", "thread"])
def test_values_write_and_a_dropped_point(master: str) -> None:
    async def main() -> tuple[list[Event], object, object]:
        with drives() as (bus, _sims):
            events: list[Event] = []
            poller = Poller(config(bus.paths[0]), master=master)  # type: ignore[attr-defined,arg-type]
            poller.on_event(events.append)
            async with poller:
                await until(lambda: any(isinstance(e, PointDropped) for e in events), "the drop")
                # writes of the WEG speed reference (P683), ahead of the polls
                await poller.write("weg.ref", 2048.0)  # scale 0.5: raw 4096
                ref = await poller.read_registers("line", 1, "holding", weg.P_REFERENCE, 1)
                await poller.write_registers("line", 1, "holding", weg.P_REFERENCE, [100])
                assert await poller.read("weg.ref") == 50.0
                # FC 16: the acceleration and deceleration times P100/P101
                await poller.write_registers("line", 1, "holding", weg.P_ACCEL_TIME, [60, 120])
                ref += await poller.read_registers("line", 1, "holding", weg.P_ACCEL_TIME, 2)
                on_demand = await poller.read("cv.status")
                names = {p.name for p in poller.config.points} - {"weg.missing"}
                await until(
                    lambda: {e.point.name for e in events if isinstance(e, Update)} >= names,
                    "every point",
                )
                return events, (ref, on_demand), poller.summary()

    events, (ref, on_demand), summary = asyncio.run(main())
    updates = {e.point.name: e for e in events if isinstance(e, Update)}
    assert set(updates) == {
        "weg.status", "weg.speed", "weg.current", "weg.fault", "weg.alarm",
        "cv.status", "cv.speed", "cv.current", "cv.fault", "weg.ref",
    }  # fmt: skip
    sim_weg = CFW701Simulator()
    assert updates["weg.fault"].value == sim_weg.store.holding_registers.get(weg.P_PRESENT_FAULT)
    assert isinstance(updates["cv.speed"].value, float)
    assert ref == [4096, 60, 120]
    assert on_demand == CV100Simulator().store.holding_registers.get(cv100.STATUS_WORD_1)
    dropped = [e.point.name for e in events if isinstance(e, PointDropped)]
    assert dropped == ["weg.missing"]
    assert [(e.slave, e.online) for e in events if isinstance(e, SlaveState)] == [
        (1, True),
        (5, True),
    ]
    assert isinstance(summary, dict) and summary["summary"] is True
    slaves = {s["slave"]: s for s in summary["slaves"]}
    assert slaves[1]["state"] == slaves[5]["state"] == "online"
    assert slaves[1]["exceptions"] >= 1  # the dropped point's
    # times are the wall clock of the answers, in order per point
    t = [e.time for e in events if isinstance(e, Update) and e.point.name == "weg.status"]
    assert t == sorted(t)


def test_a_slave_unplugged_and_replugged() -> None:
    def count(events: list[Event], slave: int, start: int = 0) -> int:
        return sum(1 for e in events[start:] if isinstance(e, Update) and e.point.slave == slave)

    def states(events: list[Event]) -> list[tuple[int, bool]]:
        return [(e.slave, e.online) for e in events if isinstance(e, SlaveState)]

    async def main() -> tuple[list[Event], int, int]:
        with drives() as (bus, sims):
            events: list[Event] = []
            poller = Poller(config(bus.paths[0]), changes_only=False)  # type: ignore[attr-defined,arg-type]
            poller.on_event(events.append)
            async with poller:
                await until(lambda: count(events, 5) >= 10, "slave 5's values")
                bus.unplug(2)  # type: ignore[attr-defined]
                sims[1].close()
                await until(lambda: (5, False) in states(events), "slave 5 offline")
                mark = len(events)
                # the CFW701 keeps being read while the CV100 is away
                await until(lambda: count(events, 1, mark) >= 30, "slave 1's values")
                absent = count(events, 5, mark)
                path = bus.replug(2)  # type: ignore[attr-defined]
                sims[1] = CV100Simulator()
                sims[1].serve(path, 5, baudrate=BAUD, parity="N")
                await until(lambda: states(events)[-1] == (5, True), "slave 5 online again")
                back = len(events)
                await until(lambda: count(events, 5, back) >= 5, "slave 5's values again")
                with contextlib.suppress(Exception):
                    sims[1].close()
                probes = poller.slave_stats()[1].requests
            return events, absent, probes

    events, absent, probes = asyncio.run(main())
    assert states(events) == [(1, True), (5, True), (5, False), (5, True)]
    assert absent == 0
    assert probes > 0


def test_noise_never_delivers_a_wrong_value() -> None:
    async def main() -> tuple[list[Event], dict[str, object]]:
        faults = Faults(seed=11, bit_flip_rate=2e-4, drop_rate=1e-3)
        with drives(faults=faults) as (bus, _sims):
            events: list[Event] = []
            poller = Poller(config(bus.paths[0], offline_after=5), changes_only=False)  # type: ignore[attr-defined,arg-type]
            poller.on_event(events.append)
            async with poller:

                def errors() -> int:
                    return sum(s.timeouts + s.frame_errors for s in poller.slave_stats())

                await until(lambda: errors() > 0 and len(events) > 200, "noise caught")
                return events, poller.summary()

    events, summary = asyncio.run(main())
    weg_regs = CFW701Simulator().store.holding_registers
    cv_regs = CV100Simulator().store.holding_registers
    expect = {
        "weg.status": weg_regs.get(weg.P_STATUS),
        "weg.fault": weg_regs.get(weg.P_PRESENT_FAULT),
        "weg.alarm": weg_regs.get(weg.P_PRESENT_ALARM),
        "cv.status": cv_regs.get(cv100.STATUS_WORD_1),
        "cv.fault": cv_regs.get(cv100.LATEST_FAULT),
    }
    got = [e for e in events if isinstance(e, Update) and e.point.name in expect]
    assert len(got) > 50
    assert all(e.value == expect[e.point.name] for e in got)
    slaves = summary["slaves"]
    assert isinstance(slaves, list)
    errors = sum(s["timeouts"] + s["frame_errors"] for s in slaves)
    assert errors > 0  # the noise was there, and was caught by CRC / timeouts


def test_rates_beyond_the_wire_are_reported() -> None:
    async def main() -> tuple[list[Event], object]:
        with drives(baud=9600) as (bus, _sims):
            events: list[Event] = []
            cfg = config(bus.paths[0], baud=9600, interval=0.002)  # type: ignore[attr-defined]
            poller = Poller(cfg, changes_only=False)  # type: ignore[arg-type]
            poller.on_event(events.append)
            async with poller:

                def served() -> bool:
                    got = Counter(e.point.slave for e in events if isinstance(e, Update))
                    return got[1] > 5 and got[5] > 5

                await until(lambda: any(isinstance(e, Overload) for e in events), "overload")
                await until(served, "both slaves served")
                return events, poller.report()[0]

    events, report = asyncio.run(main())
    over = [e for e in events if isinstance(e, Overload)]
    assert over and over[0].overloaded and over[0].load > 5
    assert report.overloaded and set(report.lagging) >= {"weg.status", "cv.status"}  # type: ignore[attr-defined]
    # both slaves are still served in turn
    got = Counter(e.point.slave for e in events if isinstance(e, Update))
    assert got[1] > 5 and got[5] > 5


def test_sync_facade() -> None:
    with drives() as (bus, _sims):
        poller = Poller(config(bus.paths[0]))  # type: ignore[attr-defined,arg-type]
        with poller.running() as p:
            first = next(p.updates(timeout=PATIENCE))
            assert isinstance(first, Update)
            assert p.read(
                "cv.fault", timeout=PATIENCE
            ) == CV100Simulator().store.holding_registers.get(cv100.LATEST_FAULT)
            give_up = time.monotonic() + PATIENCE
            while len(p.values()) < 10 and time.monotonic() < give_up:
                time.sleep(0.02)
            assert len(p.values()) == 10 and p.age("weg.status") is not None
            assert p.summary()["buses"][0]["transactions"] > 0
    # a port that cannot be opened is no error of start(): it is reported and retried
    missing = Poller(config("/nonexistent/port"))  # type: ignore[arg-type]
    seen: list[Event] = []
    missing.on_event(seen.append)
    with missing.running() as p:
        assert p.summary()["buses"][0]["port_state"] == "down"
    (down,) = seen
    assert isinstance(down, PortState) and not down.up and "nonexistent" in down.error
    # a wrong keyword is (before any port opens)
    bad = Bus("line", "/nonexistent/port", {"baudrate": 9600, "parity": "N"})
    with pytest.raises(TypeError):
        Poller(make_config([bad], profile_points("cv100", "cv", "line", 5, 1.0)),
               master=lambda b: AsyncMaster(b.port, colour="red")).running().start()  # type: ignore[call-arg]  # fmt: skip


def test_two_buses_at_once() -> None:
    async def main() -> tuple[list[Event], dict[str, object]]:
        with (
            VirtualBus(2, baudrate=BAUD, parity="N") as b1,
            VirtualBus(2, baudrate=19200, parity="N") as b2,
        ):
            s1, s2 = CFW701Simulator(), CV100Simulator()
            s1.serve(b1.paths[1], 1, baudrate=BAUD, parity="N")
            s2.serve(b2.paths[1], 5, baudrate=19200, parity="N")
            try:
                buses = [
                    Bus("fast", b1.paths[0], {"baudrate": BAUD, "parity": "N", "timeout": 0.05}),
                    Bus("slow", b2.paths[0], {"baudrate": 19200, "parity": "N", "timeout": 0.1}),
                ]
                points = profile_points("cfw701", "weg", "fast", 1, 0.05)
                points += profile_points("cv100", "cv", "slow", 5, 0.05)
                events: list[Event] = []
                poller = Poller(make_config(buses, points))
                poller.on_event(events.append)
                async with poller:

                    def seen() -> bool:
                        n = Counter(e.point.bus for e in events if isinstance(e, Update))
                        done = [r.transactions > 5 for r in poller.report()]
                        return n["fast"] == 5 and n["slow"] == 4 and all(done)

                    await until(seen, "both buses")
                    blocks = {
                        b.name: [
                            (k.table, k.count, k.interval) for k in poller.scheduler(b.name).blocks
                        ]
                        for b in buses
                    }
                    return events, poller.summary(), blocks
            finally:
                s1.close()
                s2.close()

    events, summary, blocks = asyncio.run(main())
    by_bus = Counter(e.point.bus for e in events if isinstance(e, Update))
    assert by_bus["fast"] == 5 and by_bus["slow"] == 4  # every point, change-only
    buses = summary["buses"]
    assert isinstance(buses, list) and [b["bus"] for b in buses] == ["fast", "slow"]
    assert all(b["transactions"] > 5 for b in buses)
    # Each bus's load is at least the wire time its blocks need at their rates and at
    # most that plus a full timeout per transaction: the measured turnaround, which a
    # loaded machine stretches, lies between.  The wire time from the Serial Line
    # spec: 10 bits a character at least (start, 8 data, stop), t3.5 3.5 characters
    # up to 19200 baud and 1.75 ms above (2.5.1.1); a request of 8 bytes, an answer
    # of 5 + 2 x count (Application Protocol 6.3, 6.4).
    for b, baud, timeout in zip(buses, (BAUD, 19200), (0.05, 0.1), strict=True):
        char = 10 / baud
        t35 = 3.5 * char if baud <= 19200 else 0.00175
        wire = [
            (t35 + (8 + 5 + 2 * count) * char, interval) for _t, count, interval in blocks[b["bus"]]
        ]
        assert blocks[b["bus"]] and all(t == "holding" for t, _c, _i in blocks[b["bus"]])
        low = sum(w / i for w, i in wire)
        high = sum((w + timeout) / i for w, i in wire)
        assert low <= b["load"] <= high, (b["bus"], low, b["load"], high)


def test_ascii_mode() -> None:
    async def main() -> tuple[list[Event], dict[str, object], float]:
        with VirtualBus(2, baudrate=19200, parity="N") as vb:
            sim = CV100Simulator(mode="ascii")
            sim.serve(vb.paths[1], 5, baudrate=19200, parity="N")
            try:
                options = {"baudrate": 19200, "parity": "N", "timeout": 0.3, "mode": "ascii"}
                bus = Bus("l", vb.paths[0], options)
                cfg = make_config([bus], profile_points("cv100", "cv", "l", 5, 0.1))
                events: list[Event] = []
                poller = Poller(cfg)
                poller.on_event(events.append)
                async with poller:
                    await until(lambda: len(events) >= 5, "the CV100's values")
                    return events, poller.summary(), bus.wire().t35
            finally:
                sim.close()

    events, summary, t35 = asyncio.run(main())
    cv = CV100Simulator().store.holding_registers
    values = {e.point.name: e.value for e in events if isinstance(e, Update)}
    assert values["cv.status"] == cv.get(cv100.STATUS_WORD_1)
    assert values["cv.fault"] == cv.get(cv100.LATEST_FAULT)
    assert t35 == 0.0  # ASCII frames are delimited, not timed
    (slave,) = summary["slaves"]  # type: ignore[misc]
    assert slave["state"] == "online" and slave["frame_errors"] == 0


def test_run_for_a_duration_and_the_async_iterators() -> None:
    async def main() -> tuple[list[Update], list[Event], dict[str, object]]:
        with drives() as (bus, _sims):
            poller = Poller(config(bus.paths[0]))  # type: ignore[attr-defined,arg-type]
            got: list[Update] = []
            seen: list[Event] = []

            async def consume() -> None:
                async for u in poller.updates():
                    got.append(u)

            async def watch() -> None:
                async for e in poller.events():
                    seen.append(e)

            tasks = [asyncio.create_task(consume()), asyncio.create_task(watch())]
            await asyncio.sleep(0)  # the iterators subscribe before the poller starts
            await poller.run(1.0)
            await asyncio.wait_for(asyncio.gather(*tasks), PATIENCE)  # they end with it
            return got, seen, poller.summary()

    got, seen, summary = asyncio.run(main())
    assert got and all(isinstance(u, Update) for u in got)
    assert {u.name for u in got} <= {e.point.name for e in seen if isinstance(e, Update)}
    assert any(isinstance(e, PointDropped) for e in seen)
    assert any(isinstance(e, SlaveState) for e in seen)
    assert summary["lost_events"] == 0


def test_a_probe_abandoned_by_stop_is_sent_after_a_restart() -> None:
    """Stopping while an offline slave's probe is on the wire, then starting again:
    the probe is due again (before, it stayed "in flight" and the slave was never
    probed again)."""

    async def main() -> tuple[float | None, int]:
        with drives() as (bus, _sims):
            cfg = config(bus.paths[0])
            points = [p for p in cfg.points if p.slave == 5]  # type: ignore[attr-defined]
            poller = Poller(make_config(cfg.buses, points), changes_only=False)  # type: ignore[attr-defined]
            events: list[Event] = []
            poller.on_event(events.append)
            sched = poller.scheduler("line")
            async with poller:
                await until(lambda: sched.online(5) is True, "slave 5")
                bus.unplug(2)  # type: ignore[attr-defined]
                await until(lambda: sched.online(5) is False, "slave 5 offline")
                # stop while the probe is out (it waits its timeout: no one answers)
                await until(lambda: sched.deadline() is None, "the probe on the wire")
            due = sched.deadline()
            await poller.start()  # the counts start again from 0
            try:
                await until(lambda: sched.slave_stats()[5].requests > 0, "a probe")
            finally:
                await poller.stop()
            return due, sched.slave_stats()[5].requests

    due, probes = asyncio.run(main())
    assert due is not None and probes > 0
