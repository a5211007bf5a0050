"""The simulators' registers follow the model at every look, however cheaply they are
refreshed (`pyrtu.devices._simbase.Outputs`: computed again only when the model's
inputs change, written again only when those or the table changed): a read after
time moved is fresh, also time that passed between the request's arrival and its
execution; a valid telegram brings the store to its time; a parameter written is
read back in the values that depend on it; two reads at one instant agree; the
owner's own writes to a simulator's output registers are put right at the next look."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from test_devices_sims import Direct

from pyrtu.devices import (
    ACTSimulator,
    CFW320Simulator,
    CFW701Simulator,
    CV100Simulator,
    ManualClock,
    cv100,
    weg,
)
from pyrtu.devices._simbase import Outputs
from pyrtu.protocol.datastore import DataStore


def slow_slave(d: Direct, clock: ManualClock, seconds: float = 0.1) -> None:
    """Every request takes ``seconds`` between its arrival (the simulator's telegram)
    and its execution: what a real clock shows between the two looks."""
    d.slave.on_request(lambda unit, pdu: clock.advance(seconds))


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(1000.0)


@pytest.fixture
def cv(clock: ManualClock) -> Iterator[Direct]:
    d = Direct(CV100Simulator(clock=clock, state="stopped"), unit=5)
    yield d
    d.close()


def _cv100_ramping(d: Direct) -> CV100Simulator:
    sim = d.sim
    assert isinstance(sim, CV100Simulator)
    assert d.write(cv100.register("A0.06"), 10, 10) == 0  # 1.0 s from 0 to 50.00 Hz
    assert d.write(cv100.CONTROL_WORD_1, 0x00C7) == 0  # start forward
    return sim


# -- CV100 ---------------------------------------------------------------------------------


def test_cv100_read_after_time_moved_is_fresh(cv: Direct, clock: ManualClock) -> None:
    _cv100_ramping(cv)
    seen = []
    for _ in range(4):
        clock.advance(0.1)
        seen.append(cv.read(cv100.STATUS_WORD_1, 10))
    assert [s[5] for s in seen] == [500, 1000, 1500, 2000]  # operating frequency
    assert [s[6] for s in seen] == [30, 60, 90, 120]  # output current, 0.1 A
    assert len({s[0] for s in seen}) == 1  # status word 1: running, accelerating
    clock.advance(1)
    at_reference = cv.read(cv100.STATUS_WORD_1, 10)
    assert at_reference[5] == 5000 and at_reference[0] != seen[0][0]  # bit 2: at reference


def test_cv100_two_reads_at_one_instant_agree(cv: Direct, clock: ManualClock) -> None:
    _cv100_ramping(cv)
    clock.advance(0.37)
    first = cv.read(cv100.STATUS_WORD_1, 35)
    assert first == cv.read(cv100.STATUS_WORD_1, 35)
    assert first[5] == 1850


def test_cv100_read_sees_the_time_after_the_telegram(cv: Direct, clock: ManualClock) -> None:
    """The answer is the model when the read executes, not when the request came."""
    slow_slave(cv, clock)
    _cv100_ramping(cv)  # the ramp starts when the control word is executed
    assert [cv.read(cv100.OPERATING_FREQUENCY)[0] for _ in range(4)] == [500, 1000, 1500, 2000]


def test_cv100_telegram_shows_the_model_in_the_store(cv: Direct, clock: ManualClock) -> None:
    """Any valid telegram (here FC 08, which reads no register) brings the registers
    the owner reads from the store to the telegram's time."""
    sim = _cv100_ramping(cv)
    clock.advance(0.5)
    assert cv.pdu(b"\x08\x00\x00\x12\x34") == b"\x08\x00\x00\x12\x34"
    assert int(sim.store.holding_registers.get(cv100.OPERATING_FREQUENCY)) == 2500


def test_cv100_written_parameters_read_back_in_the_status(cv: Direct, clock: ManualClock) -> None:
    assert cv.read(cv100.ACCEL_TIME_1, 2) == [60, 60]
    assert cv.write(cv100.register("A0.06"), 123) == 0
    assert cv.read(cv100.ACCEL_TIME_1, 2) == [123, 60]
    assert cv.write(cv100.DECEL_TIME_SETTING, 45) == 0  # the control parameter writes A0.07
    assert cv.read(cv100.ACCEL_TIME_1, 2) == [123, 45]
    assert cv.write(cv100.MAIN_SETTING, 2000) == 0
    assert cv.read(cv100.MAIN_REFERENCE) == [5000]  # the keypad's setting: bit 8 not set
    assert cv.write(cv100.CONTROL_WORD_1, 0x00C6 | cv100.CW1_MAIN_REFERENCE) == 0
    assert cv.read(cv100.MAIN_REFERENCE) == [2000]
    assert cv.read(cv100.MAIN_REFERENCE_SELECTOR) == [2]


def test_cv100_owner_changes_show_at_the_next_look(cv: Direct, clock: ManualClock) -> None:
    sim = cv.sim
    assert isinstance(sim, CV100Simulator)
    regs = sim.store.holding_registers
    before = cv.read(cv100.STATUS_WORD_1, 35)
    regs.set(cv100.OPERATING_FREQUENCY, 4321)  # the owner overwrites an output register
    regs.set_each({cv100.STATUS_WORD_1: 0xFFFF, cv100.LATEST_FAULT: 99})
    assert cv.read(cv100.STATUS_WORD_1, 35) == before  # the model's values again
    sim.inject_fault(33)
    assert int(regs.get(cv100.LATEST_FAULT)) == 33 and int(regs.get(cv100.FIRST_FAULT)) == 33
    assert cv.read(cv100.STATUS_WORD_1)[0] >> 8 == 33
    sim.inject_fault(7)
    assert cv.read(cv100.FIRST_FAULT, 3) == [33, 7, 7]


def test_cv100_power_cycle_and_undervoltage_show(cv: Direct, clock: ManualClock) -> None:
    sim = _cv100_ramping(cv)
    clock.advance(2)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [5000]
    sim.power_cycle()
    assert cv.read(cv100.OPERATING_FREQUENCY) == [0] and cv.read(cv100.ACCEL_TIME_1) == [60]
    with sim.lock:
        sim.undervoltage = True
    assert cv.read(cv100.BUS_VOLTAGE) == [400]  # an attribute the owner set, seen by a read


# -- WEG -----------------------------------------------------------------------------------


def test_weg_read_after_time_moved_is_fresh(clock: ManualClock) -> None:
    d = Direct(CFW701Simulator(clock=clock))
    try:
        assert d.write(100, 50, 50) == 0  # 5.0 s ramps
        assert d.write(683, weg.hz_to_13bit(30, 60)) == 0
        assert d.write(682, weg.control_word(run=True)) == 0
        seen = []
        for _ in range(3):
            clock.advance(1.0)
            seen.append(d.read(1, 7))
        # P005: output frequency (0.1 Hz), P002: speed (Hz); 66 Hz in 5 s
        assert [s[4] for s in seen] == [132, 264, 300]
        assert [s[1] for s in seen] == [13, 26, 30]
        assert d.read(1, 7) == seen[-1]  # same instant, same values
    finally:
        d.close()


def test_weg_read_sees_the_time_after_the_telegram(clock: ManualClock) -> None:
    d = Direct(CFW701Simulator(clock=clock))
    try:
        slow_slave(d, clock)
        assert d.write(100, 50, 50) == 0  # 5.0 s ramps: 13.2 Hz/s
        assert d.write(683, weg.hz_to_13bit(30, 60)) == 0
        assert d.write(682, weg.control_word(run=True)) == 0
        assert [d.read(5)[0] for _ in range(4)] == [13, 26, 40, 53]  # P005: 0.1 Hz
    finally:
        d.close()


def test_weg_telegram_shows_the_model_in_the_store(clock: ManualClock) -> None:
    d = Direct(CFW320Simulator(clock=clock))
    try:
        regs = d.sim.store.holding_registers
        assert int(regs.get(316)) == weg.InterfaceStatus.INACTIVE  # no traffic yet
        assert d.pdu(b"\x2b\x0e\x01\x00")[0] == 0x2B  # FC 43 reads no register
        assert int(regs.get(316)) == weg.InterfaceStatus.ACTIVE
    finally:
        d.close()


def test_weg_written_parameters_and_the_watchdog_show(clock: ManualClock) -> None:
    d = Direct(CFW701Simulator(clock=clock))  # stopped
    try:
        sim = d.sim
        assert isinstance(sim, CFW701Simulator)
        assert d.write(401, 40) == 0  # rated current 4.0 A (CFG: while stopped)
        assert d.write(314, 300) == 0  # watchdog 30.0 s
        assert d.write(683, weg.hz_to_13bit(30, 60)) == 0
        assert d.read(1) == [0]  # P001: speed reference, 0.1 Hz
        assert d.write(682, weg.control_word(run=True)) == 0
        assert d.read(1) == [300]
        clock.advance(10)
        assert d.read(3) == [20]  # P003: 4.0 A x 30 Hz / 60 Hz
        assert d.write(683, weg.hz_to_13bit(45, 60)) == 0
        assert d.read(1) == [450]
        assert d.read(316) == [1]  # interface active
        clock.advance(30.5)
        assert d.read(316) == [2]  # the first telegram after the timeout sees it
        assert d.read(316) == [1]  # and the next one the interface active again
        sim.store.holding_registers.set(680, 0)  # the owner overwrites the status word
        assert d.read(680) == [sim.get(680)] != [0]
    finally:
        d.close()


# -- Bonfiglioli ---------------------------------------------------------------------------


def test_bonfiglioli_read_sees_the_time_after_the_telegram(clock: ManualClock) -> None:
    d = Direct(ACTSimulator(clock=clock))
    try:
        slow_slave(d, clock)
        assert d.pdu(b"\x65\x01\xa4" + (1000).to_bytes(4, "big"))[0] == 0x65  # 420: 10 Hz/s
        assert d.pdu(b"\x65\x01\xe4" + (3000).to_bytes(4, "big"))[0] == 0x65  # 484: 30 Hz
        assert d.write(410, 0x0F) == 0
        seen = []
        for _ in range(3):
            resp = d.pdu(b"\x64\x00\xf1")  # FC 100 of 241: actual frequency (0.01 Hz)
            seen.append(int.from_bytes(resp[1:5], "big", signed=True))
        assert seen == [100, 200, 300]
    finally:
        d.close()


# -- the cache -----------------------------------------------------------------------------


def test_outputs_compute_on_new_inputs_write_on_changes() -> None:
    store = DataStore()
    regs = store.holding_registers
    regs.add_range(0, [0] * 4)
    computed: list[tuple[int, int]] = []

    def compute(inputs: tuple[int, int]) -> dict[int, int]:
        computed.append(inputs)
        a, b = inputs
        return {0: a, 2: b, 3: a + b}

    out = Outputs(regs, compute)
    with store.lock:
        out.show((1, 2))
        assert regs.get_many(0, 4) == [1, 0, 2, 3] and computed == [(1, 2)]
        version = regs.version
        out.show((1, 2))  # nothing changed: nothing computed, nothing written
        assert computed == [(1, 2)] and regs.version == version
        regs.set(3, 40)  # the table changed: written again, not computed
        regs.set(1, 9)
        out.show((1, 2))
        assert regs.get_many(0, 4) == [1, 9, 2, 3] and computed == [(1, 2)]
        regs.write(0, [7])  # a request's write counts too
        out.show((1, 2))
        assert regs.get(0) == 1 and computed == [(1, 2)]
        out.show((5, 2))
        assert regs.get_many(0, 4) == [5, 9, 2, 7] and computed == [(1, 2), (5, 2)]
