"""The simulators' behaviour, on a manual clock: function codes and exception cases,
ranges and read-only parameters, ramps, control words and state machines, faults,
the serial watchdog.  Requests go through each simulator's `pyrtu.Slave` on a
``loop://`` port (one `Slave.poll` per request), so no time passes unless the test
moves the clock."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import pyrtu
from pyrtu.devices import (
    ACTSimulator,
    ACUSimulator,
    CFW100Simulator,
    CFW320Simulator,
    CFW701Simulator,
    CV100Simulator,
    DriveSimulator,
    DriveState,
    ManualClock,
    bonfiglioli,
    cv100,
    weg,
)
from pyrtu.devices.common import u16


class Direct:
    """A simulator's slave on ``loop://``: PDU in, PDU out."""

    def __init__(self, sim: DriveSimulator, unit: int = 1) -> None:
        self.sim = sim
        self.unit = unit
        self.slave = sim.make_slave("loop://", unit, parity="N", t35=0, response_delay=0)

    def pdu(self, request: bytes) -> bytes:
        self.slave.port.write(pyrtu.add_crc(bytes([self.unit]) + request))
        self.slave.poll(0.2)
        adu = self.slave.port.read(0.2)
        assert adu and pyrtu.check_crc(adu) and adu[0] == self.unit, adu
        return adu[1:-2]

    def _read(self, address: int, count: int, fc: int) -> bytes:
        return self.pdu(bytes([fc]) + address.to_bytes(2, "big") + count.to_bytes(2, "big"))

    def read(self, address: int, count: int = 1, fc: int = 3) -> list[int]:
        resp = self._read(address, count, fc)
        assert not resp[0] & 0x80, f"exception {resp[1]} reading {address}"
        return [int.from_bytes(resp[2 + 2 * i : 4 + 2 * i], "big") for i in range(count)]

    def refused(self, address: int, count: int = 1, fc: int = 3) -> int:
        """The exception code of a read (0: it succeeded)."""
        resp = self._read(address, count, fc)
        return resp[1] if resp[0] & 0x80 else 0

    def write(self, address: int, *values: int) -> int:
        """0 on success, else the exception code."""
        if len(values) == 1:
            req = b"\x06" + address.to_bytes(2, "big") + u16(values[0]).to_bytes(2, "big")
        else:
            body = b"".join(u16(v).to_bytes(2, "big") for v in values)
            req = b"\x10" + address.to_bytes(2, "big") + len(values).to_bytes(2, "big")
            req += bytes([len(body)]) + body
        resp = self.pdu(req)
        return resp[1] if resp[0] & 0x80 else 0

    def close(self) -> None:
        self.slave.close()


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(1000.0)


@pytest.fixture
def cfw701(clock: ManualClock) -> Iterator[Direct]:
    d = Direct(CFW701Simulator(clock=clock))
    yield d
    d.close()


# -- WEG ------------------------------------------------------------------------------------

#: a well-formed request of every standard function (data after the function code)
REQUESTS = {
    1: "0000 0001", 2: "0000 0001", 3: "0000 0001", 4: "0000 0001", 5: "0000 FF00",
    6: "0000 0000", 7: "", 8: "0000 0000", 15: "0000 0001 01 01", 16: "0000 0001 02 0000",
    17: "", 22: "0000 FFFF 0000", 23: "0000 0001 0000 0001 02 0000", 43: "0E 01 00",
}  # fmt: skip


def test_weg_function_codes_per_model(clock: ManualClock) -> None:
    for cls, supported in (
        (CFW100Simulator, {3, 4, 6, 16, 43}),
        (CFW320Simulator, {1, 2, 3, 5, 6, 15, 16, 22, 23, 43}),
        (CFW701Simulator, {1, 2, 3, 4, 5, 6, 15, 16, 43}),
    ):
        d = Direct(cls(clock=clock))
        try:
            for fc, data in REQUESTS.items():
                resp = d.pdu(bytes([fc]) + bytes.fromhex(data))
                refused = resp[0] == fc | 0x80 and resp[1] == 1
                assert refused == (fc not in supported), (cls.__name__, fc, resp)
        finally:
            d.close()


def test_weg_exception_cases(cfw701: Direct) -> None:
    assert cfw701.write(2900, 0) == 2  # nonexistent
    assert cfw701.write(680, 0) == 3  # read only
    assert cfw701.write(316, 0) == 3
    assert cfw701.write(314, 9991) == 3  # out of range
    assert cfw701.write(695, 0x20) == 3  # CFW701: 5 digital outputs
    assert cfw701.write(100, 0, 20) == 3  # FC 16: one bad value, nothing written
    assert cfw701.read(100, 2) == [50, 100]
    assert cfw701.refused(2900) == 2
    assert cfw701.write(683, u16(-4096)) == 0 and cfw701.read(683) == [u16(-4096)]


#: every parameter number each WEG manual names (``P\d{3,4}`` in seeds 000, 001, 002)
MANUAL_PARAMETERS = {
    "CFW100": (0, 1, 2, 3, 48, 49, 100, 101, 102, 103, 105, *range(220, 229), 308, 310, 311,
               313, 314, 316, 403, 680, 681, 682, 683),
    "CFW320": (0, 1, 6, 28, 48, 49, 100, 101, 102, 103, 220, 221, 222, 228, 251, 254, 308,
               310, 311, 312, 313, 314, 316, 402, 403, 680, 681, 682, 683, 685, 695, 696, 697),
    "CFW701": (0, 1, 48, 49, 100, 101, 102, 103, 105, 202, *range(220, 229), 251, 254, 275,
               279, 308, 310, 311, 312, 313, 314, 316, 680, 681, 682, 683, 695, 696, 697),
}  # fmt: skip


@pytest.mark.parametrize("model", sorted(MANUAL_PARAMETERS))
def test_weg_maps_every_parameter_its_manual_names(model: str, clock: ManualClock) -> None:
    """The manual is the spec: a parameter it names answers FC 03 (exception 2 would
    be a simulator bug), also those it only refers to (P028, P202, P251/P254,
    P275-P279); P2900 (the manual's nonexistent register) still answers 2."""
    d = Direct({"CFW100": CFW100Simulator, "CFW320": CFW320Simulator,
                "CFW701": CFW701Simulator}[model](clock=clock))  # fmt: skip
    try:
        missing = [n for n in MANUAL_PARAMETERS[model] if d.refused(n) != 0]
        assert missing == []
        assert d.refused(2900) == 2
        if model == "CFW701":
            assert d.read(275, 5) == [0] * 5  # DO1-DO5 functions, one block
            assert d.write(279, 10) == 0 and d.read(279) == [10]
            assert d.write(202, 6) == 3  # out of the simulator's range
        if model == "CFW320":
            assert d.write(28, 1) == 3  # read only
            assert d.refused(275) == 2  # the CFW320 manual names no P275
    finally:
        d.close()


def test_weg_64_byte_telegram_limit(cfw701: Direct) -> None:
    """A read whose response would pass 64 bytes (30 registers: 65) is refused with
    exception 3, before the address check (29 registers at P680 run into a gap: 2)."""
    assert cfw701.refused(680, 4) != 3
    assert cfw701.refused(680, 30) == 3
    assert cfw701.refused(680, 29) == 2
    assert cfw701.refused(680, 30, fc=4) == 3
    # a request longer than 64 bytes is not a telegram: no answer at all
    body = bytes(2 * 28)
    req = b"\x10\x00\x64\x00\x1c\x38" + body
    cfw701.slave.port.write(pyrtu.add_crc(b"\x01" + req))
    cfw701.slave.poll(0.05)
    assert cfw701.slave.port.read(0.05) == b""


def test_weg_identification(clock: ManualClock) -> None:
    d = Direct(CFW320Simulator(clock=clock))
    try:
        resp = d.pdu(b"\x2b\x0e\x01\x00")
        assert resp == b"\x2b\x0e\x01\x81\x00\x00\x03" + b"\x00\x03WEG\x01\x06CFW320\x02\x05V1.00"
        assert d.pdu(b"\x2b\x0e\x04\x01") == b"\x2b\x0e\x04\x81\x00\x00\x01\x01\x06CFW320"
        assert d.pdu(b"\x2b\x0e\x02\x00") == b"\xab\x03"  # regular: not supported
        assert d.pdu(b"\x2b\x0e\x04\x07") == b"\xab\x02"
    finally:
        d.close()


def test_cfw_reaches_30hz_after_the_ramp(cfw701: Direct, clock: ManualClock) -> None:
    sim = cfw701.sim
    assert isinstance(sim, CFW701Simulator)
    assert cfw701.write(100, 20, 20) == 0  # 2.0 s from 0 to P134 = 66.0 Hz
    assert cfw701.write(683, weg.hz_to_13bit(30, 60)) == 0
    assert cfw701.write(682, weg.control_word(run=True)) == 0
    assert weg.decode_status(cfw701.read(680)[0]).describe() == "running, forward, remote"
    ramp = 30 / 66 * 2.0
    assert sim.ramp_time_left() == pytest.approx(ramp)
    clock.advance(ramp / 2)
    assert sim.speed_hz() == pytest.approx(15.0)
    clock.advance(ramp / 2)
    assert weg.hz_from_13bit(cfw701.read(681)[0], 60) == pytest.approx(30.0, abs=0.01)
    assert cfw701.read(2, 2) == [30, 15]  # P002 30 Hz, P003 1.5 A
    assert cfw701.write(403, 50) == 3  # CFG while running
    assert cfw701.write(682, weg.control_word(run=False)) == 0
    clock.advance(0.5)  # decelerating: 66 Hz in 2 s
    assert sim.speed_hz() == pytest.approx(30 - 33.0 * 0.5)
    clock.advance(0.5)
    assert sim.speed_hz() == 0.0
    assert weg.decode_status(cfw701.read(680)[0]).describe() == "stopped, forward, remote"


def test_cfw_direction_jog_disable_and_local(cfw701: Direct, clock: ManualClock) -> None:
    sim = cfw701.sim
    assert isinstance(sim, CFW701Simulator)
    cfw701.write(100, 1, 1)
    cfw701.write(683, weg.hz_to_13bit(-30, 60))
    cfw701.write(682, weg.control_word(run=True))
    clock.advance(5)
    assert sim.speed_hz() == pytest.approx(-30.0)
    assert not sim.status().forward
    cfw701.write(682, weg.control_word(run=True, forward=False))  # bit 2 = 0 inverts: forward
    clock.advance(5)
    assert sim.speed_hz() == pytest.approx(30.0) and sim.status().forward
    cfw701.write(682, weg.control_word(jog=True))
    clock.advance(5)
    assert sim.speed_hz() == pytest.approx(-5.0) and sim.status().jog  # P122 = 5.0 Hz, bit 2 = 1
    cfw701.write(682, weg.control_word(run=True, enable=False))
    assert sim.speed_hz() == 0.0 and not sim.status().enabled  # coasts at once
    cfw701.write(682, weg.control_word(run=True, remote=False))
    clock.advance(5)
    st = sim.status()
    assert not st.remote and not st.running and sim.speed_hz() == 0.0  # the keypad holds no run


def test_cfw100_manual_state_and_second_ramp(clock: ManualClock) -> None:
    d = Direct(CFW100Simulator(clock=clock))
    try:
        assert d.read(2, 2) == [30, 15]
        assert d.read(680) == [0x1700] and d.read(681) == [4096]
        assert d.read(680, fc=4) == [0x1700]  # FC 04 reads the same parameters
        d.write(102, 1, 1)
        d.write(682, weg.control_word(run=True, second_ramp=True))
        d.write(683, weg.hz_to_13bit(60, 60))
        clock.advance(0.1)  # second ramp: 0.1 s for 66 Hz
        assert d.read(2) == [60] and d.read(680)[0] & 0x20  # status bit 5: second ramp
    finally:
        d.close()


def test_cfw320_reference_at_p683_and_p685(clock: ManualClock) -> None:
    d = Direct(CFW320Simulator(clock=clock))
    sim = d.sim
    assert isinstance(sim, CFW320Simulator)
    try:
        assert sim.get(316) == 0  # no valid traffic yet
        assert d.read(316) == [1]  # the request itself is valid traffic
        d.write(685, weg.hz_to_13bit(20, 60))
        assert d.read(683) == [weg.hz_to_13bit(20, 60)]
        d.write(683, weg.hz_to_13bit(10, 60))
        assert d.read(685) == [weg.hz_to_13bit(10, 60)]
        d.write(100, 1)
        d.write(682, weg.control_word(run=True))
        clock.advance(1)
        assert sim.speed_hz() == pytest.approx(10.0, abs=0.01)
        st = sim.status()
        assert st.run_command and st.fire_mode is False and d.read(680)[0] & 0x2
        d.write(695, 0xF)
        assert d.write(695, 0x10) == 3
        resp = d.pdu(b"\x05\x00\x03\xff\x00")  # SoftPLC marker 3 on, then read it as input
        assert resp == b"\x05\x00\x03\xff\x00"
        assert d.pdu(b"\x02\x00\x00\x00\x08") == b"\x02\x01\x08"
        assert d.pdu(b"\x16\x02\xaa\xff\xfe\x00\x00")[0] == 0x16  # FC 22 on P682: bit 0 off
        assert sim.status().run_command is False
    finally:
        d.close()


@pytest.mark.parametrize(
    ("action", "expect"),
    [
        (weg.ErrorAction.RAMP_STOP, {"alarm": True, "running": True, "enabled": True}),
        (weg.ErrorAction.GENERAL_DISABLE, {"alarm": True, "running": False, "enabled": False}),
        (weg.ErrorAction.GO_TO_LOCAL, {"alarm": True, "remote": False, "running": True}),
        (weg.ErrorAction.CAUSE_FAULT, {"fault": True, "alarm": False, "running": False}),
        (weg.ErrorAction.INACTIVE, {"alarm": True, "running": True}),
    ],
)
def test_weg_watchdog(cfw701: Direct, clock: ManualClock, action: weg.ErrorAction,
                      expect: dict[str, bool]) -> None:  # fmt: skip
    sim = cfw701.sim
    assert isinstance(sim, CFW701Simulator)
    cfw701.write(100, 10, 10)  # 1 s ramps
    cfw701.write(313, int(action))
    cfw701.write(314, 5)  # 0.5 s
    cfw701.write(683, weg.hz_to_13bit(30, 60))
    cfw701.write(682, weg.control_word(run=True))
    clock.advance(0.45)
    assert sim.status().alarm is False and sim.speed_hz() > 0  # fed in time
    clock.advance(0.06)  # 0.51 s after the last telegram, 0.01 s after the timeout
    st = sim.status()
    for name, value in expect.items():
        assert getattr(st, name) is value, (name, st)
    assert sim.get(316) == int(weg.InterfaceStatus.WATCHDOG_ERROR)
    assert sim.get(48 if action is not weg.ErrorAction.CAUSE_FAULT else 49) in (128, 228)
    # the first telegram after the timeout still sees it; then an alarm clears
    assert cfw701.read(316) == [2]
    assert cfw701.read(316) == [1]
    if action is weg.ErrorAction.CAUSE_FAULT:
        assert cfw701.read(49) == [228] and sim.status().fault
        cfw701.write(682, weg.control_word(fault_reset=True))
        assert cfw701.read(49) == [0] and not sim.status().fault
    else:
        assert cfw701.read(48) == [0]


def test_weg_watchdog_counts_from_first_telegram(clock: ManualClock) -> None:
    sim = CFW701Simulator(clock=clock)
    sim.set(314, 5)
    clock.advance(100)
    assert not sim.status().alarm  # no valid telegram yet
    sim.telegram()
    clock.advance(0.49)
    assert not sim.status().alarm
    clock.advance(0.02)
    assert sim.status().alarm and sim.get(48) == 128


def test_weg_fault_and_undervoltage(cfw701: Direct, clock: ManualClock) -> None:
    sim = cfw701.sim
    assert isinstance(sim, CFW701Simulator)
    cfw701.write(682, weg.control_word(run=True))
    cfw701.write(683, 4096)
    clock.advance(5)
    sim.inject_fault(70)
    assert sim.status().fault and sim.speed_hz() == 0.0 and cfw701.read(6) == [3]
    cfw701.write(682, weg.control_word(run=True, fault_reset=True))
    clock.advance(5)
    assert not sim.status().fault and sim.speed_hz() == pytest.approx(30.0)
    sim.set_undervoltage(True)
    st = sim.status()
    assert st.undervoltage and not st.running and cfw701.read(4) == [200]


# -- CV100 -----------------------------------------------------------------------------------


@pytest.fixture
def cv(clock: ManualClock) -> Iterator[Direct]:
    d = Direct(CV100Simulator(clock=clock, state="stopped"), unit=5)
    yield d
    d.close()


def test_cv100_run_stop_jog_reset(cv: Direct, clock: ManualClock) -> None:
    sim = cv.sim
    assert isinstance(sim, CV100Simulator)
    cv.write(cv100.register("A0.06"), 10, 10)  # 1.0 s from 0 to 50.00 Hz
    assert cv.write(cv100.CONTROL_WORD_1, 0x00C7) == 0  # start forward
    clock.advance(0.5)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [2500]
    st = sim.status()
    assert st.word1.running and not st.word1.reverse and "accelerating" in st.word3
    clock.advance(0.5)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [5000] and sim.status().word1.at_reference
    assert cv.read(cv100.OUTPUT_CURRENT) == [300]
    cv.write(cv100.CONTROL_WORD_1, 0x00C6)  # stop mode 0
    clock.advance(0.5)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [2500] and "decelerating" in sim.status().word3
    clock.advance(1)
    assert not sim.status().word1.running
    cv.write(cv100.CONTROL_WORD_1, 0x00D0)  # jog forward at 5.00 Hz
    clock.advance(1)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [500] and "jog" in sim.status().word2
    cv.write(cv100.CONTROL_WORD_1, 0x00C0)  # stop jogging
    clock.advance(1)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [0]
    cv.write(cv100.CONTROL_WORD_1, 0x00CC)  # 100B: external fault
    st = sim.status()
    assert st.word1.fault and st.word1.code == 15 and "failure" in st.word3
    cv.write(cv100.CONTROL_WORD_1, 0x00C7)  # ignored in a fault
    clock.advance(1)
    assert cv.read(cv100.OPERATING_FREQUENCY) == [0] and cv.read(cv100.LATEST_FAULT) == [15]
    cv.write(cv100.CONTROL_WORD_1, 0x0280)  # reset fault
    assert not sim.status().word1.fault
    assert cv.read(cv100.CONTROL_WORD_1) == [0x0280]  # control parameters read back


def test_cv100_reverse_main_reference_and_control_word_2(cv: Direct, clock: ManualClock) -> None:
    sim = cv.sim
    assert isinstance(sim, CV100Simulator)
    cv.write(cv100.register("A0.06"), 1, 1)
    cv.write(cv100.MAIN_SETTING, 2000)
    cv.write(
        cv100.CONTROL_WORD_1, 0x00CF | cv100.CW1_MAIN_REFERENCE
    )  # run reverse on the main setting
    clock.advance(1)
    assert sim.frequency_hz() == pytest.approx(-20.0)
    assert cv.read(cv100.MAIN_REFERENCE) == [2000] and sim.status().word1.reverse
    assert sim.status().word1.serial_setting
    assert cv.write(cv100.MAIN_SETTING, 6000) == 3  # above the maximum frequency
    cv.write(cv100.CONTROL_WORD_2, 0b1001)  # control word 2 enabled: operation disable
    assert sim.frequency_hz() == 0.0 and not sim.status().word1.running


def test_cv100_exceptions_and_partial_writes(cv: Direct) -> None:
    assert cv.refused(0x0900) == 2  # no group 0x09
    assert cv.read(cv100.register("A0.63")) == [0] and cv.refused(0x0040) == 2
    assert cv.write(cv100.STATUS_WORD_1, 1) == 3  # status parameters are read only
    assert cv.write(cv100.register("B4.04"), 1) == 4  # reserved: cannot be changed
    assert cv.write(cv100.register("A0.06"), 0) == 3
    # function codes: one bad value and nothing is written
    assert cv.write(cv100.register("A0.05"), 7, 100, 0) == 3
    assert cv.read(cv100.register("A0.05"), 3) == [0, 60, 60]
    # control parameters: the ones before the bad one are written
    assert cv.write(cv100.MAIN_SETTING, 1234, 9999) == 3
    assert cv.read(cv100.MAIN_SETTING, 2) == [1234, 0]
    assert cv.refused(0x3204) == 2  # "do not support"
    assert cv.refused(cv100.STATUS_WORD_3) != 2 and cv.refused(0x3323) == 2


def test_cv100_saved_writes_and_power_cycle(cv: Direct) -> None:
    sim = cv.sim
    assert isinstance(sim, CV100Simulator)
    a006, a007 = cv100.register("A0.06"), cv100.register("A0.07")
    assert cv.write(a006, 100) == 0  # FC 06: lost at power-off
    assert cv.pdu(b"\x41" + a007.to_bytes(2, "big") + (123).to_bytes(2, "big"))[0] == 0x41
    body = (11).to_bytes(2, "big") + (22).to_bytes(2, "big")
    resp = cv.pdu(b"\x43" + cv100.register("A2.00").to_bytes(2, "big") + b"\x00\x02\x04" + body)
    assert resp == b"\x43\x02\x00\x00\x02"
    cv.write(cv100.register("A2.03"), 9)  # always saved, even by FC 06
    sim.power_cycle()
    assert cv.read(a006, 2) == [60, 123]
    assert cv.read(cv100.register("A2.00"), 4) == [11, 22, 0, 9]


def test_cv100_manage(cv: Direct) -> None:
    a006 = cv100.register("A0.06").to_bytes(2, "big")
    assert cv.pdu(b"\x42\x00\x00" + a006) == b"\x42\x00\x00" + (36000).to_bytes(2, "big")
    assert cv.pdu(b"\x42\x00\x01" + a006) == b"\x42\x00\x01\x00\x01"
    assert cv.pdu(b"\x42\x00\x02" + a006) == b"\x42\x00\x02\x00\x3c"
    assert cv.pdu(b"\x42\x00\x06\x33\x06") == b"\x42\x00\x06\x33\x06"
    assert cv.pdu(b"\x42\x00\x05\x00\x00") == b"\x42\x00\x05\x33\x06"
    assert cv.pdu(b"\x42\x00\x09\x00\x00") == b"\xc2\x01"
    assert cv.pdu(b"\x42\x00\x00\x09\x00") == b"\xc2\x02"


def test_cv100_passwords(clock: ManualClock) -> None:
    d = Direct(CV100Simulator(clock=clock, user_password=1234, factory_password=42), unit=5)
    try:
        a006 = cv100.register("A0.06")
        assert d.refused(a006) == 4 and d.write(a006, 10) == 4
        assert d.refused(cv100.STATUS_WORD_1) != 4  # status parameters are not protected
        assert d.write(cv100.register("A0.00"), 1111) == 4
        assert d.write(cv100.register("A0.00"), 1234) == 0
        assert d.read(a006) == [60] and d.read(cv100.register("A0.00")) == [0]
        clock.advance(299)
        assert d.read(a006) == [60]  # each telegram keeps the right for 5 minutes
        clock.advance(301)
        assert d.refused(a006) == 4
        u001 = cv100.register("U0.01")
        d.write(cv100.register("A0.00"), 1234)
        assert d.refused(u001) == 4
        assert d.write(cv100.register("U0.00"), 42) == 0 and d.read(u001) == [0]
    finally:
        d.close()


# -- Bonfiglioli ----------------------------------------------------------------------------


@pytest.fixture
def act(clock: ManualClock) -> Iterator[Direct]:
    d = Direct(ACTSimulator(clock=clock, fault_lock_time=1.0))
    yield d
    d.close()


def _fc101(d: Direct, parameter: int, value: int, data_set: int = 0) -> bytes:
    return d.pdu(
        b"\x65"
        + bonfiglioli.address(parameter, data_set).to_bytes(2, "big")
        + (value & 0xFFFFFFFF).to_bytes(4, "big")
    )


def _fc100(d: Direct, parameter: int, data_set: int = 0) -> int:
    resp = d.pdu(b"\x64" + bonfiglioli.address(parameter, data_set).to_bytes(2, "big"))
    return -resp[1] if resp[0] & 0x80 else int.from_bytes(resp[1:5], "big", signed=True)


def test_bonfiglioli_state_machine_walk(act: Direct, clock: ManualClock) -> None:
    sim = act.sim
    assert isinstance(sim, ACTSimulator)
    assert act.read(411)[0] & 0x6F == 0x40
    _fc101(act, 420, 10000)  # 100.00 Hz/s
    _fc101(act, 421, 10000)
    _fc101(act, 484, 3000)  # 30.00 Hz
    seen = []
    for word in (0x06, 0x07, 0x0F):
        assert act.write(410, word) == 0
        seen.append(act.read(411)[0] & 0x6F)
    assert seen == [0x21, 0x23, 0x27]
    clock.advance(0.3)
    assert _fc100(act, 210) == 3000 and sim.status().reference_reached and sim.status().remote
    sim.fault(0x0500)
    assert act.read(411)[0] & 0x6F == 0x08 and act.read(260) == [0x0500]
    assert sim.frequency_hz() == 0.0
    act.write(410, 0x80)  # within the blocking time: no reset
    act.write(410, 0x00)
    assert sim.status().state is DriveState.FAULT
    clock.advance(1.0)
    act.write(410, 0x80)  # positive edge after the blocking time
    assert sim.status().state is DriveState.STARTING_LOCKOUT and act.read(260) == [0]


def test_bonfiglioli_transition_5_ramp_and_quick_stop(act: Direct, clock: ManualClock) -> None:
    sim = act.sim
    assert isinstance(sim, ACTSimulator)
    _fc101(act, 420, 5000)
    _fc101(act, 421, 5000)  # 50 Hz/s
    _fc101(act, 424, 10000)  # emergency: 100 Hz/s
    _fc101(act, 484, 2500)
    act.write(410, 0x0F)  # from 0x40 straight to operation enabled (the extension)
    clock.advance(1)
    assert sim.frequency_hz() == pytest.approx(25.0)
    act.write(410, 0x07)  # disable operation: ramp (392 = 2) ...
    clock.advance(0.2)
    assert (
        sim.status().state is DriveState.OPERATION_ENABLED
        and sim.frequency_hz() == pytest.approx(15.0)
    )
    clock.advance(0.28 + 0.99)  # ... below the threshold (0.5 Hz at 0.49 s), holding time 1.0 s
    assert sim.status().state is DriveState.OPERATION_ENABLED
    clock.advance(0.02)
    assert sim.status().state is DriveState.SWITCHED_ON
    act.write(410, 0x0F)
    clock.advance(1)
    act.write(410, 0x02)  # quick stop along the emergency ramp
    assert act.read(411)[0] & 0x6F == 0x07
    clock.advance(0.1)
    assert sim.frequency_hz() == pytest.approx(15.0)
    clock.advance(1.5)
    assert sim.status().state is DriveState.STARTING_LOCKOUT


def test_bonfiglioli_watchdog_f2010(act: Direct, clock: ManualClock) -> None:
    sim = act.sim
    assert isinstance(sim, ACTSimulator)
    assert act.write(413, 2) == 0  # 2 s, counting from this telegram
    act.write(410, 0x0F)
    clock.advance(1.9)
    assert sim.status().state is DriveState.OPERATION_ENABLED
    clock.advance(0.2)
    assert sim.status().state is DriveState.FAULT
    assert act.read(260) == [bonfiglioli.F2010]
    clock.advance(2)
    act.write(410, 0x00)
    act.write(410, 0x80)
    assert sim.status().state is DriveState.STARTING_LOCKOUT


def test_bonfiglioli_exceptions_and_error_register(act: Direct) -> None:
    assert act.refused(bonfiglioli.address(372, 2), 2) == 2  # No. of Registers must be 1
    assert act.refused(bonfiglioli.address(1600)) == 4 and act.read(11) == [
        11
    ]  # unknown; then cleared:
    assert act.read(11) == [0]
    assert act.refused(bonfiglioli.address(484)) == 3  # a long parameter through FC 03
    assert _fc100(act, 372) == -3
    assert act.write(411, 0) == 4 and act.read(11) == [4]  # read only
    assert act.write(bonfiglioli.address(376, 2), 0) == 4 and act.read(11) == [1]  # out of range
    assert act.refused(0xA000 | 376) == 4 and act.read(11) == [2]  # data set 10
    assert act.refused(bonfiglioli.address(413, 2)) == 4 and act.read(11) == [2]  # no data sets
    assert act.write(bonfiglioli.address(376, 4), 15) == 0
    assert act.refused(bonfiglioli.address(376)) == 4 and act.read(11) == [9]  # data sets differ
    assert act.read(bonfiglioli.address(376, 4)) == [15] and act.read(
        bonfiglioli.address(376, 1)
    ) == [11]
    assert act.write(bonfiglioli.address(376), 20) == 0 and act.read(bonfiglioli.address(376)) == [
        20
    ]
    act.write(410, 0x0F)  # running: rated data refused
    assert act.write(bonfiglioli.address(372, 1), 1400) == 4 and act.read(11) == [8]
    assert act.pdu(b"\x04\x00\x00\x00\x01") == b"\x84\x01"  # FC 04 is not supported
    assert act.pdu(b"\x08\x00\x00\x12\x34") == b"\x88\x01"  # return query data: not supported
    assert act.pdu(b"\x08\x00\x0b\x00\x01") == b"\x88\x03"  # data field not 0


def test_bonfiglioli_ram_data_sets_and_power_cycle(act: Direct) -> None:
    sim = act.sim
    assert isinstance(sim, ACTSimulator)
    writes = sim.eeprom_writes
    assert act.write(bonfiglioli.address(376, 2, ram=True), 30) == 0  # data set 2 + 5: RAM only
    assert sim.eeprom_writes == writes
    assert act.read(bonfiglioli.address(376, 2)) == [30]
    assert act.write(bonfiglioli.address(376, 3), 40) == 0
    assert sim.eeprom_writes == writes + 1
    act.write(34, 123)  # Programming 34 = 123: software reset
    assert act.read(bonfiglioli.address(376, 2)) == [11] and act.read(
        bonfiglioli.address(376, 3)
    ) == [40]


def test_acu_specifics(clock: ManualClock) -> None:
    d = Direct(ACUSimulator(clock=clock))
    try:
        status = d.read(411)[0]
        assert (
            status & 0x10
            and status & 0x6F == 0x40
            and bonfiglioli.state_of(status) is DriveState.STARTING_LOCKOUT
        )
        assert _fc101(d, 484, 1000)[0] == 0x65
        assert _fc100(d, 484) == -4 and d.read(11) == [3]  # write only on the ACU
        assert _fc100(d, 241) == 0
    finally:
        d.close()


def test_bonfiglioli_counters(act: Direct) -> None:
    assert act.pdu(b"\x08\x00\x0a\x00\x00") == b"\x08\x00\x0a\x00\x00"
    assert act.refused(bonfiglioli.address(1600)) == 4
    assert act.pdu(b"\x08\x00\x0d\x00\x00") == b"\x08\x00\x0d\x00\x01"  # exception responses
    assert act.pdu(b"\x08\x00\x0e\x00\x00") == b"\x08\x00\x0e\x00\x03"  # slave messages
    assert act.pdu(b"\x08\x00\x10\x00\x00") == b"\x08\x00\x10\x00\x00"  # NAK: always 0


def test_broadcast_writes_execute_without_answer(clock: ManualClock) -> None:
    """Bonfiglioli 6.1: "All devices must accept the broadcast for writing function"."""
    act = Direct(ACTSimulator(clock=clock))
    cv = Direct(CV100Simulator(clock=clock), unit=5)
    try:
        for d, pdu in (
            (
                act,
                b"\x65" + bonfiglioli.address(484).to_bytes(2, "big") + (1234).to_bytes(4, "big"),
            ),
            (act, b"\x06" + bonfiglioli.address(413).to_bytes(2, "big") + (7).to_bytes(2, "big")),
            (cv, b"\x41" + cv100.register("A0.06").to_bytes(2, "big") + (77).to_bytes(2, "big")),
        ):
            d.slave.port.write(pyrtu.add_crc(b"\x00" + pdu))
            d.slave.poll(0.2)
            assert d.slave.port.read(0.05) == b""
        assert _fc100(act, 484) == 1234 and act.read(413) == [7]
        assert cv.read(cv100.register("A0.06")) == [77]
        # a broadcast read is not executed
        act.slave.port.write(
            pyrtu.add_crc(b"\x00\x03" + bonfiglioli.address(413).to_bytes(2, "big") + b"\x00\x01")
        )
        act.slave.poll(0.2)
        assert act.slave.port.read(0.05) == b""
    finally:
        act.close()
        cv.close()
