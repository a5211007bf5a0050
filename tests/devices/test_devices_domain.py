"""The drives' domain logic, without I/O: scales, words, addressing, state machine,
parameter tables, the motor model and the supervision timer."""

from __future__ import annotations

import math

import pytest

from pyrtu.devices import bonfiglioli, cv100, weg
from pyrtu.devices.common import s16, s32, scaled, u16, u32, unscaled
from pyrtu.devices.motor import ManualClock, Motor, Supervision, Timeline
from tests.vectors import TELEGRAMS

# -- WEG ----------------------------------------------------------------------------


def test_13bit_scale_examples() -> None:
    # CFW100 P683: 30 Hz of a 60 Hz motor is 4096 (1000h, the FC 06 example); P681 2048 is 15 Hz
    assert weg.hz_to_13bit(30, 60) == 0x1000
    assert weg.hz_from_13bit(0x0800, 60) == 15.0
    assert weg.hz_to_13bit(60, 60) == 8192
    # CFW701 wording: 900 rpm of 1800 rpm synchronous speed is 4096, 2048 reads 450 rpm
    assert weg.rpm_to_13bit(900, 1800) == 4096
    assert weg.rpm_from_13bit(2048, 1800) == 450.0


def test_13bit_scale_saturates_and_signs() -> None:
    assert weg.hz_to_13bit(4 * 60, 60) == 32767
    assert weg.hz_to_13bit(1000, 60) == 32767
    assert weg.hz_to_13bit(-1000, 60) == -32768
    assert weg.hz_to_13bit(-30, 60) == -4096
    assert weg.hz_from_13bit(u16(-4096), 60) == -30.0
    assert weg.hz_from_13bit(0xF000, 60) == -30.0
    with pytest.raises(ValueError):
        weg.hz_to_13bit(10, 0)


def test_status_word_common_layout() -> None:
    st = weg.decode_status(0b1001_0111_1010_0000, "CFW701")
    assert st.fault and st.remote and st.forward and st.enabled and st.running
    assert st.alarm and st.second_ramp
    assert not (st.jog or st.undervoltage or st.config_mode)
    assert st.run_command is None and st.fire_mode is None
    assert weg.decode_status(0x1700).describe() == "running, forward, remote"
    assert weg.decode_status(0x0000, "CFW100").describe() == "stopped, reverse, local, disabled"


def test_status_word_cfw320_bits_differ() -> None:
    # bits 1 (run command) and 2 (fire mode) exist only on the CFW320
    cfw320 = weg.decode_status(0x0006, "CFW320")
    assert cfw320.run_command is True and cfw320.fire_mode is True
    other = weg.decode_status(0x0006, "CFW100")
    assert other.run_command is None and other.active() == []
    assert weg.encode_status(cfw320, "CFW320") == 0x0006
    assert weg.encode_status(cfw320, "CFW701") == 0


def test_control_word_builder() -> None:
    assert weg.control_word(run=True) == 0x17  # run, enable, direction as reference, remote
    assert weg.control_word(enable=False, remote=False, forward=False) == 0
    assert weg.control_word(fault_reset=True, jog=True) == 0x9E
    assert weg.WegControl(second_ramp=True, forward=False).encode("CFW100") == 0x20
    assert weg.WegControl(fast_stop=True, forward=False).encode("CFW701") == 0x40
    with pytest.raises(ValueError, match="fast_stop"):
        weg.WegControl(fast_stop=True).encode("CFW100")
    assert weg.WegControl.decode(0xE0FF, "CFW701").pid_external2_manual
    assert not weg.WegControl.decode(0xE0FF, "CFW100").pid_external2_manual


@pytest.mark.parametrize(
    ("bit2", "reference", "forward"),
    [(True, 100, True), (True, -100, False), (False, 100, False), (False, -100, True)],
)
def test_reference_direction_table(bit2: bool, reference: int, forward: bool) -> None:
    """The four lines of the P683 direction table."""
    assert weg.reference_direction(4 if bit2 else 0, u16(reference)) is forward


def test_error_actions_write_the_control_word() -> None:
    full = 0x3F
    assert weg.apply_error_action(full, weg.ErrorAction.RAMP_STOP) == 0x3E
    assert weg.apply_error_action(full, weg.ErrorAction.GENERAL_DISABLE) == 0x3D
    assert weg.apply_error_action(full, weg.ErrorAction.GO_TO_LOCAL) == 0x2F
    assert weg.apply_error_action(full, weg.ErrorAction.LOCAL_KEEP_COMMANDS) == 0x2F
    assert weg.apply_error_action(full, weg.ErrorAction.INACTIVE) == full
    assert weg.apply_error_action(full, weg.ErrorAction.CAUSE_FAULT) == full


def test_weg_parameter_tables() -> None:
    cfw100, cfw320, cfw701 = (weg.parameters(m) for m in ("CFW100", "CFW320", "CFW701"))
    for table in (cfw100, cfw320, cfw701):
        assert table[680].ro and table[681].ro and table[316].ro
        assert not table[682].ro and table[683].accepts(u16(-32768))
        assert table[314].cfg and table[314].accepts(9990) and not table[314].accepts(9991)
        assert 2900 not in table
    assert 685 in cfw320 and 685 not in cfw701 and 695 not in cfw100
    assert cfw701[695].high == 0x1F and cfw320[695].high == 0xF
    assert cfw100[310].high == 2 and cfw320[310].high == 4 and cfw701[310].high == 3
    assert cfw701[311].default == 0 and cfw100[311].default == 1
    assert weg.CFW320_MODEL.functions == frozenset({1, 2, 3, 5, 6, 15, 16, 22, 23, 43})
    assert weg.CFW100_MODEL.functions == frozenset({3, 4, 6, 16, 43})


def test_weg_describe_register() -> None:
    assert weg.describe_register("CFW701", 680, 0x1700) == "P680 status: running, forward, remote"
    assert weg.describe_register("CFW701", 316, 2) == "P316 serial interface: watchdog_error"
    assert weg.describe_register("CFW320", 685, 4096) == "P685 reference: 4096/8192 of P403"
    assert weg.describe_register("CFW701", 100, 10) is None


# -- CV100 ----------------------------------------------------------------------------


def test_cv100_addressing() -> None:
    assert cv100.register("A3.02") == 0x0302
    assert cv100.register("a0.06") == 0x0006
    assert cv100.register("B0.00") == 0x0A00 and cv100.register("B4.02") == 0x0E02
    assert cv100.register("C1.05") == 0x1505 and cv100.register("D2.00") == 0x2000
    assert cv100.register("U0.09") == 0x5A09
    assert cv100.register("A6.28") == 0x061C
    assert cv100.register(0x3200) == 0x3200
    assert cv100.function_code(0x0302) == "A3.02" and cv100.function_code(0x3301) == "0x3301"
    for bad in ("A9.00", "C2.00", "X1.00", "A3-", "A3.123"):
        with pytest.raises(ValueError):
            cv100.register(bad)


@pytest.mark.parametrize(
    ("word", "value"),
    [
        (cv100.ControlWord1(cv100.Command.RUN), 0x00C7),  # start forward
        (cv100.ControlWord1(cv100.Command.STOP), 0x00C6),  # stop mode 0
        (cv100.ControlWord1(jog_forward=True), 0x00D0),  # jog forward
        (cv100.ControlWord1(), 0x00C0),  # stop jogging
        (cv100.ControlWord1(acc_dec_enable=False, fault_reset=True), 0x0280),  # reset fault
    ],
)
def test_cv100_control_word_1_examples(word: cv100.ControlWord1, value: int) -> None:
    assert word.encode() == value
    assert cv100.ControlWord1.decode(value) == word
    # and the value is what the manual's telegram carries
    assert any(t.adu[2:6] == bytes([0x32, 0x00, value >> 8, value & 0xFF]) for t in TELEGRAMS)


def test_cv100_control_word_2_and_status_words() -> None:
    assert cv100.ControlWord2(run=True).encode() == 0b1010
    assert cv100.ControlWord2.decode(0b1101) == cv100.ControlWord2(True, False, True, True)
    w1 = cv100.StatusWord1.decode(0x0F0B)
    assert w1.running and w1.reverse and w1.serial_control and not w1.alarm
    assert w1.code == 0x0F and w1.fault
    alarm = cv100.StatusWord1.decode(0x0381)
    assert alarm.alarm and not alarm.fault and alarm.code == 3
    assert cv100.StatusWord1.decode(0x0F0B).encode() == 0x0F0B
    assert cv100.flags(0b1000001, cv100.STATUS_2_BITS) == {"jog", "undervoltage"}
    assert cv100.flags(1 << 12 | 1 << 3, cv100.STATUS_3_BITS) == {"failure", "accelerating"}
    assert cv100.flags_word(["failure", "accelerating"], cv100.STATUS_3_BITS) == 1 << 12 | 1 << 3


#: the manuals' bit tables: CV100 status word 1 (section 6.1) and Vectron status word 411
CV100_STATUS_1_BITS = {
    0: "running", 1: "reverse", 2: "at_reference", 3: "serial_control", 4: "serial_setting",
    7: "alarm",
}  # fmt: skip
VECTRON_STATUS_BITS = {
    0: "ready", 1: "switched_on", 2: "operation_enabled", 3: "fault", 4: "voltage",
    5: "quick_stop", 6: "starting_lockout", 7: "warning", 9: "remote", 10: "reference_reached",
    11: "limit_active", 15: "warning2",
}  # fmt: skip


def test_each_status_flag_is_its_bit_of_the_word() -> None:
    for bit in range(16):
        one = 1 << bit
        cv = cv100.StatusWord1.decode(one)
        assert cv.active() == ([CV100_STATUS_1_BITS[bit]] if bit in CV100_STATUS_1_BITS else [])
        assert cv.code == one >> 8
        assert cv.encode() == (one if bit in CV100_STATUS_1_BITS or bit >= 8 else 0)
        vectron = bonfiglioli.VectronStatus.decode(one)
        assert vectron.word == one
        expected = [VECTRON_STATUS_BITS[bit]] if bit in VECTRON_STATUS_BITS else []
        assert vectron.active() == expected
    assert cv100.StatusWord1(0, running=True, alarm=True, code=0x12).encode() == 0x1281


def test_cv100_scalings() -> None:
    assert cv100.raw_hz(50) == 0x1388 and cv100.hz(0x1388) == 50.0
    assert cv100.raw_seconds(30) == 0x012C and cv100.seconds(0x0064) == 10.0
    assert cv100.amperes(0x012C) == 30.0
    assert cv100.describe_register(cv100.OUTPUT_CURRENT, 300) == "output current: 30.0 A"
    assert (
        cv100.describe_register(cv100.STATUS_WORD_1, 0x0F00)
        == "status word 1: stopped, forward, fault 15"
    )


# -- Bonfiglioli ------------------------------------------------------------------------


def test_bonfiglioli_addressing() -> None:
    assert bonfiglioli.address(372, 2) == 0x2174
    assert bonfiglioli.address(376, 4) == 0x4178
    assert bonfiglioli.address(481) == 0x01E1
    assert bonfiglioli.address(375, 2) == 0x2177
    assert bonfiglioli.address(484, 0, ram=True) == 0x51E4
    assert bonfiglioli.address(1599, 4, ram=True) == 0x963F  # the top of the manual's 0x0000-0x963F
    assert bonfiglioli.split(0x2640) == (2, 1600)
    with pytest.raises(ValueError):
        bonfiglioli.address(372, 5, ram=True)
    with pytest.raises(ValueError):
        bonfiglioli.address(0x1000)


def test_chapter_11_parameter_list() -> None:
    chapter_11 = {228, 229, 249, 250, 260, 270, 282, 283, 411}  # 11.1 actual values
    chapter_11 |= {10, 11, 34, 392, 394, 395, 410, 412, 413, 414, 424, 425, 434}  # 11.2
    chapter_11 |= {484, 524, 549, 632, 637, 638, 1375, 1376}
    assert chapter_11 <= set(bonfiglioli.PARAMETERS)
    p = bonfiglioli.PARAMETERS
    assert p[413].high == 10000 and p[413].type is bonfiglioli.Type.UINT
    assert p[484].type is bonfiglioli.Type.LONG and (p[484].low, p[484].high) == (-99999, 99999)
    assert p[524].decimals == 2 and p[524].high == 30000
    assert p[1376].low == 1 and p[1376].high == 247
    assert not p[411].writable and p[410].ram_only
    # the examples' parameters: 372 no decimals, 376 one, 375 and 481 two
    assert (p[372].decimals, p[376].decimals, p[375].decimals, p[481].decimals) == (0, 1, 2, 2)
    assert p[375].to_raw(10.0) == 1000 and p[376].from_raw(15) == 1.5
    assert 1600 not in p


def test_drivecom_walk_and_transitions() -> None:
    S = bonfiglioli.DriveState
    walk = [
        (0x06, S.READY, 2),
        (0x07, S.SWITCHED_ON, 3),
        (0x0F, S.OPERATION_ENABLED, 4),
        (0x07, S.SWITCHED_ON, 5),
        (0x06, S.READY, 6),
        (0x00, S.STARTING_LOCKOUT, 7),
    ]
    state = S.STARTING_LOCKOUT
    for word, expected, transition in walk:
        state, t = bonfiglioli.next_state(state, word)
        assert (state, t) == (expected, transition)
    assert bonfiglioli.next_state(S.STARTING_LOCKOUT, 0x0F) == (
        S.OPERATION_ENABLED,
        4,
    )  # the extension
    assert bonfiglioli.next_state(S.OPERATION_ENABLED, 0x06) == (S.READY, 8)
    assert bonfiglioli.next_state(S.OPERATION_ENABLED, 0x00) == (S.STARTING_LOCKOUT, 9)
    assert bonfiglioli.next_state(S.SWITCHED_ON, 0x00) == (S.STARTING_LOCKOUT, 10)
    assert bonfiglioli.next_state(S.OPERATION_ENABLED, 0x02) == (S.QUICK_STOP, 11)
    assert bonfiglioli.next_state(S.QUICK_STOP, 0x00) == (S.STARTING_LOCKOUT, 12)
    assert bonfiglioli.next_state(S.FAULT, 0x0F) == (S.FAULT, None)
    assert bonfiglioli.next_state(S.READY, 0x06) == (S.READY, None)


def test_status_word_decoding() -> None:
    for value in (0x40, 0x21, 0x23, 0x27, 0x07, 0x08, 0x0F):
        assert bonfiglioli.state_of(value) == value
        assert bonfiglioli.state_of(value | 0x10 | 0x0680) == value  # bit 4 and bits 7..15 ignored
    st = bonfiglioli.VectronStatus.decode(0x0627)
    assert (
        st.state is bonfiglioli.DriveState.OPERATION_ENABLED and st.remote and st.reference_reached
    )
    assert st.describe() == "operation enabled, remote, reference reached"
    assert (
        bonfiglioli.fault_text(bonfiglioli.F2010) == "F2010"
        and bonfiglioli.fault_text(0x0102) == "F0102"
    )
    assert bonfiglioli.warnings_of(0x008B) == ["Ixt", "Short-Term Ixt", "Heat Sink Temperature Tk",
                                     "Motor Temperature"]  # fmt: skip


def test_word_helpers() -> None:
    assert u16(-1) == 0xFFFF and s16(0xFFFF) == -1 and s16(0x7FFF) == 32767
    assert u32(-2) == 0xFFFFFFFE and s32(0xFFFFFFFE) == -2
    assert unscaled(10.3, 1) == 103 and unscaled(100.25, 2) == 10025 and scaled(103, 1) == 10.3
    with pytest.raises(ValueError):
        u16(0x10000)


# -- motor model and supervision -----------------------------------------------------------


def test_motor_ramps_up_and_down() -> None:
    m = Motor.from_times(60.0, accel_s=2.0, decel_s=4.0)  # 30 Hz/s up, 15 Hz/s down
    m.reference = 30.0
    assert m.time_to_reference() == pytest.approx(1.0)
    m.advance(0.5)
    assert m.frequency == pytest.approx(15.0)
    m.advance(10)
    assert m.frequency == 30.0 and m.at_reference
    m.reference = 0.0
    m.advance(1.0)
    assert m.frequency == pytest.approx(15.0)


def test_motor_reverses_through_zero() -> None:
    m = Motor(accel=10.0, decel=20.0, frequency=10.0, reference=-10.0)
    assert m.time_to_reference() == pytest.approx(0.5 + 1.0)
    assert m.time_to(0.0) == pytest.approx(0.5)
    assert m.time_to(5.0) == pytest.approx(0.25)
    m.advance(1.0)
    assert m.frequency == pytest.approx(-5.0)
    assert m.time_to(20.0) == math.inf


def test_motor_step_and_coast() -> None:
    m = Motor.from_times(50.0, 0.0, 0.0)
    m.reference = 40.0
    m.advance(0.0)
    assert m.frequency == 40.0
    m.coast()
    assert m.frequency == 0.0


def test_supervision_counts_from_first_telegram() -> None:
    sup = Supervision(timeout=2.0)
    assert sup.deadline() is None  # not counting before the first valid telegram
    sup.feed(10.0)
    assert sup.deadline() == 12.0
    sup.feed(11.0)
    assert sup.deadline() == 13.0
    sup.tripped = True
    assert sup.deadline() is None
    sup.reset()
    assert sup.last is None and not sup.tripped


def test_timeline_stops_at_events() -> None:
    clock = ManualClock(100.0)
    line = Timeline(clock)
    seen: list[tuple[str, float]] = []
    pending = [101.0, 102.5]

    def nxt() -> float | None:
        return pending[0] if pending else None

    def fire(at: float) -> None:
        seen.append(("fire", at))
        pending.pop(0)

    clock.advance(2.0)
    assert line.run(None, nxt, lambda dt: seen.append(("advance", dt)), fire) == 102.0
    assert seen == [("advance", 1.0), ("fire", 101.0), ("advance", 1.0)]
    with pytest.raises(ValueError):
        clock.advance(-1)


def test_registry_and_describe() -> None:
    from pyrtu.devices import EXAMPLE_ADDRESS, PROFILES, SIMULATORS, describe_register, simulator

    assert set(SIMULATORS) == set(PROFILES) == set(EXAMPLE_ADDRESS)
    assert set(SIMULATORS) == {"cfw100", "cfw320", "cfw701", "cv100", "act", "acu"}
    assert type(simulator("ACU")).__name__ == "ACUSimulator"
    with pytest.raises(ValueError, match="unknown device"):
        simulator("cfw500")
    with pytest.raises(ValueError, match="the rtu mode only"):
        simulator("cfw701", mode="ascii")
    with pytest.raises(ValueError, match="the rtu and ascii modes only"):
        simulator("act", mode="tcp")
    assert describe_register("cfw320", 680, 0x1502) == (
        "P680 status: running, forward, remote, disabled"
    )
    assert describe_register("acu", bonfiglioli.P_STATUS_WORD, 0x0237) == (
        "411 status: operation enabled, remote (0x0237)"
    )
    assert describe_register("act", bonfiglioli.address(484), u32(-1234)) == (
        "484 Reference Frequency RAM (data set 0): -12.34 Hz"
    )
    assert describe_register("cv100", cv100.MAIN_REFERENCE, 5000) == (
        "Current main reference value: 50.00 Hz"
    )
    with pytest.raises(ValueError):
        describe_register("x", 0, 0)
