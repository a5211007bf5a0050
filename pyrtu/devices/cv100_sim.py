"""Simulated CV100 / FV100 on `pyrtu.Slave`, RTU or ASCII (seed 003).

What the manual gives, and the simulator does:

* function codes 0x03, 0x06, 0x08, 0x10 and the vendor codes 0x41/0x43 (the same
  writes, kept after power-off: `power_cycle` shows the difference) and 0x42;
* registers by group/index (groups A0-A8, B0-B4, C0-C1, D0-D2, U0), control
  parameters at 0x32xx (read back as last written), status parameters at 0x33xx
  (read only);
* FC 0x10/0x43 on function codes: one invalid value and nothing is written; on
  control parameters: the ones before the invalid one are written;
* the function codes that are always kept (B4.02, A6.00-A6.04, A2.03, B0.00, U0.01,
  U0.09) and the reserved ones that cannot be changed (B4.04, B0.11);
* the user password (A0.00) and the factory password (U0.00, group U0) with the
  5-minute access right; reading either returns 0;
* control word 1 (bits 0-2 command, 3 direction, 4/5 jog, 6 acc/dec bits enable,
  7 control word enable, 8 main reference, 9 fault reset) and control word 2; in a
  fault only the reset acts; status words 1-3 follow the motor model; ramps are
  the acceleration/deceleration times 1 (A0.06/A0.07) from 0 to the maximum
  frequency; scalings 1:100 Hz, 1:10 s, 1:10 A;
* the response delay: 3.5 characters in RTU (the slave's t3.5), 1 ms in ASCII.

Choices where the manual is silent: exception 2 for an address the drive does not
have (each group has the indices 0-63), 3 for a value out of range or a write to a
status parameter, 4 for an operation the drive refuses (password, reserved code);
status word 3 at 0x3322; the maximum frequency is 50.00 Hz and the jog frequency
5.00 Hz (constructor arguments); the output current is the rated current (30.0 A)
x |f| / maximum frequency; an external-fault stop shows fault code 15; the
sub-functions of 0x42 are those of `cv100.Manage`.  The default state is the
manual's examples': running forward at the main reference 50.00 Hz, 30.0 A, A1.01 =
5000, deceleration time 1 = 6.0 s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

from pyrtu.core.rules import CV100 as CV100_RULES
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import SlaveException

from .. import pdu as pdus
from . import cv100
from ._simbase import DriveSimulator, HandlerSpec, Outputs
from .motor import Clock, monotonic

GROUP_SIZE = 64
ACCESS_SECONDS = 300.0
FAULT_EXTERNAL = 15

# the function codes the simulator reads or writes itself
A0_00 = cv100.register("A0.00")  # user password
A0_06 = cv100.register("A0.06")  # acceleration time 1
A0_07 = cv100.register("A0.07")  # deceleration time 1
U0_00 = cv100.register("U0.00")  # factory password


@dataclass(frozen=True)
class Code:
    name: str
    default: int = 0
    low: int = 0
    high: int = 0xFFFF
    always_saved: bool = False
    reserved: bool = False


KNOWN: dict[int, Code] = {
    A0_00: Code("User password"),
    A0_06: Code("Acceleration time 1", 60, 1, 36000),
    A0_07: Code("Deceleration time 1", 60, 1, 36000),
    cv100.register("A1.01"): Code("A1.01 (read in the manual's RTU example)", 5000),
    cv100.register("A2.01"): Code("A2.01 (written in the manual's ASCII example)"),
    cv100.register("A2.03"): Code("Main reference frequency control", always_saved=True),
    **{
        cv100.register(f"A6.0{i}"): Code(f"Selection of input terminal X{i + 1}", always_saved=True)
        for i in range(5)
    },
    cv100.register("B0.00"): Code("Motor rated power", always_saved=True),
    cv100.register("B0.11"): Code("Motor parameters auto-tuning", reserved=True),
    cv100.register("B4.02"): Code("Parameters protection setting", always_saved=True),
    cv100.register("B4.04"): Code("Parameters copy", reserved=True),
    U0_00: Code("Factory password"),
    cv100.register("U0.01"): Code("Machine model setting", always_saved=True),
    cv100.register("U0.09"): Code("VFD series selection", always_saved=True),
}
_CONTROL_RANGES = ((0x3200, 4), (0x3205, 1), (0x3207, 1), (0x3209, 3), (0x3212, 1))
_STATUS_FIRST, _STATUS_LAST = cv100.STATUS_WORD_1, cv100.STATUS_WORD_3


class _StatusInputs(NamedTuple):
    """Everything the status parameters (0x33xx) are computed from."""

    frequency: float  # the motor's, signed Hz
    reference: float
    run: bool
    jog: str | None
    reverse: bool
    main_reference: bool
    reference_hz: float
    command_source: int
    fault_code: int
    alarm_code: int
    undervoltage: bool
    first_fault: int
    second_fault: int
    latest_fault: int
    max_hz: float
    rated_current: float
    accel_time: int  # A0.06, raw
    decel_time: int  # A0.07, raw


# status words 2 and 3: name -> bit (`cv100.flags_word` of one name)
_BIT_2 = {name: 1 << bit for bit, name in cv100.STATUS_2_BITS.items()}
_BIT_3 = {name: 1 << bit for bit, name in cv100.STATUS_3_BITS.items()}


def _status_parameters(s: _StatusInputs) -> dict[int, int]:
    """The status parameters' values (address -> value), from ``s`` alone."""
    f = abs(s.frequency)
    running = f != 0.0 or ((s.run or s.jog is not None) and s.reference != 0.0)
    if s.frequency or s.reference:
        reverse = (s.frequency or s.reference) < 0
    else:
        reverse = s.reverse if s.run else s.jog == "reverse"
    at_ref = running and s.frequency == s.reference and s.jog is None
    code = s.fault_code or s.alarm_code
    w1 = cv100.StatusWord1(
        0,
        running,
        reverse,
        at_ref,
        s.command_source == 2,
        s.main_reference,
        bool(s.alarm_code),
        code,
    )
    w2 = _BIT_2["jog"] if running and s.jog else _BIT_2["common"] if running else 0
    if s.undervoltage:
        w2 |= _BIT_2["undervoltage"]
    w3 = _BIT_3["speed_control"]
    if running:
        w3 |= _BIT_3[
            "constant_speed"
            if at_ref and f
            else "zero_speed"
            if not f
            else "accelerating"
            if abs(s.reference) > f
            else "decelerating"
        ]
    if s.fault_code:
        w3 |= _BIT_3["failure"]
    current = s.rated_current * f / s.max_hz if s.max_hz else 0.0
    voltage = 380.0 * f / s.max_hz if s.max_hz else 0.0
    values = {
        cv100.STATUS_WORD_1: w1.encode(),
        cv100.MAIN_REFERENCE: round(s.reference_hz * 100),
        cv100.SLAVE_MODEL: 100,
        cv100.VFD_MODEL: 1,
        cv100.SOFTWARE_VERSION: 100,
        cv100.OPERATING_FREQUENCY: round(f * 100),
        cv100.OUTPUT_CURRENT: round(current * 10),
        cv100.OUTPUT_VOLTAGE: round(voltage),
        cv100.OUTPUT_POWER: round(1.732 * voltage * current * 0.85 / 100),
        cv100.ROTARY_SPEED: round(f * 30),
        cv100.BUS_VOLTAGE: 400 if s.undervoltage else 540,
        cv100.OUTPUT_TORQUE: round(100 * f / s.max_hz) if s.max_hz else 0,
        cv100.FIRST_FAULT: s.first_fault,
        cv100.SECOND_FAULT: s.second_fault,
        cv100.LATEST_FAULT: s.latest_fault,
        cv100.FREQUENCY_SETTING: round(abs(s.reference) * 100),
        0x3316: round(abs(s.reference) * 30),
        cv100.ACCEL_TIME_1: s.accel_time,
        cv100.DECEL_TIME_1: s.decel_time,
        cv100.COMMAND_SOURCE: s.command_source,
        cv100.STATUS_WORD_2: w2,
        cv100.MAIN_REFERENCE_SELECTOR: 2 if s.main_reference else 0,
        cv100.STATUS_WORD_3: w3,
    }
    return {a: v & 0xFFFF for a, v in values.items()}


class CV100Simulator(DriveSimulator):
    """A CV100/FV100.  ``mode``: "rtu" or "ascii" (sets the response delay)."""

    device = "cv100"
    example_addresses = frozenset({5})
    modes = ("rtu", "ascii")

    def __init__(
        self,
        *,
        state: str = "manual",
        mode: str = "rtu",
        max_hz: float = 50.0,
        jog_hz: float = 5.0,
        rated_current: float = 30.0,
        user_password: int = 0,
        factory_password: int = 8888,
        clock: Clock = monotonic,
    ) -> None:
        super().__init__(mode=mode, clock=clock)
        if state not in ("manual", "stopped"):
            raise ValueError("state is 'manual' or 'stopped'")
        self.max_hz = max_hz
        self.jog_hz = jog_hz
        self.rated_current = rated_current
        self.user_password = user_password
        self.factory_password = factory_password
        self.preset_hz = 50.0  # the keypad's digital setting (main reference without bit 8)
        self.command_source = 2  # 0x331E: communication control
        self.fault_code = 0
        self.alarm_code = 0
        self.undervoltage = False
        self.fault_log: list[int] = []
        self.run = state == "manual"
        self.reverse = False
        self.jog: str | None = None
        self.main_reference = False
        self.operation_disabled = False
        self.aux_reference = False
        self.display = cv100.OPERATING_FREQUENCY
        self._user_until = -1.0
        self._factory_until = -1.0
        self._saving = False
        #: the status parameters (0x33xx), shown by `_refresh`
        self._status = Outputs(self.store.holding_registers, _status_parameters)
        regs = self.store.holding_registers
        self.eeprom: dict[int, int] = {}
        for high in cv100.GROUPS.values():
            base = high << 8
            values = [KNOWN[a].default if a in KNOWN else 0 for a in range(base, base + GROUP_SIZE)]
            regs.add_range(
                base,
                values,
                validator=self._validate_code,
                on_write=self._on_write_code,
                on_read=self._on_read_code,
            )
            self.eeprom.update(zip(range(base, base + GROUP_SIZE), values, strict=True))
        for start, n in _CONTROL_RANGES:
            regs.add_range(
                start, [0] * n, validator=self._validate_control, on_write=self._on_write_control
            )
        regs.add_range(
            _STATUS_FIRST,
            [0] * (_STATUS_LAST - _STATUS_FIRST + 1),
            read_only=True,
            on_read=self._on_read_status,
        )
        with self.lock:
            self._retarget()
            self.motor.frequency = self.motor.reference
            self._refresh()

    # -- access rights and values -------------------------------------------------------

    def _raw(self, address: int) -> int:
        return int(self.store.holding_registers.get(address))

    def _check_access(self, address: int, writing: bool) -> None:
        now = self.timeline.now
        if address >> 8 == cv100.GROUPS["U0"] and address != U0_00:
            if now > self._factory_until:
                raise SlaveException(4, "group U0 needs the factory password in U0.00")
        elif address != A0_00 and self.user_password and now > self._user_until:
            raise SlaveException(4, "function codes need the user password in A0.00")

    def _on_read_code(self, address: int, count: int) -> None:
        self.update()
        for a in range(address, address + count):
            self._check_access(a, False)
        for pw in (A0_00, U0_00):
            if address <= pw < address + count:
                self.store.holding_registers.set(pw, 0)

    def _validate_code(self, address: int, value: int | bool) -> bool:
        value = int(value)
        if address == A0_00:
            ok = value == self.user_password if self.user_password else value == 0
            if not ok:
                raise SlaveException(4, "the user password cannot be set or changed by the host")
            return True
        if address == U0_00:
            if value != self.factory_password:
                raise SlaveException(4, "wrong factory password")
            return True
        self._check_access(address, True)
        code = KNOWN.get(address)
        if code is None:
            return True
        if code.reserved:
            raise SlaveException(4, f"{code.name} cannot be changed via communication")
        return code.low <= value <= code.high

    def _on_write_code(self, address: int, values: list[int | bool]) -> None:
        now = self.update()
        for a, v in zip(range(address, address + len(values)), values, strict=True):
            if a == A0_00:
                if self.user_password:
                    self._user_until = now + ACCESS_SECONDS
                continue
            if a == U0_00:
                self._factory_until = now + ACCESS_SECONDS
                continue
            code = KNOWN.get(a)
            if self._saving or (code is not None and code.always_saved):
                self.eeprom[a] = int(v)
        self._retarget()

    def _validate_control(self, address: int, value: int | bool) -> bool:
        value = int(value)
        if address in (cv100.MAIN_SETTING, cv100.OPERATION_FREQUENCY_SETTING):
            return value <= round(self.max_hz * cv100.FREQUENCY_SCALE)
        if address in (cv100.ACCEL_TIME_SETTING, cv100.DECEL_TIME_SETTING):
            return 1 <= value <= 36000
        return True

    def _on_write_control(self, address: int, values: list[int | bool]) -> None:
        self.update()
        for a, v in zip(range(address, address + len(values)), values, strict=True):
            self._control(a, int(v))
        self._retarget()

    def _control(self, address: int, value: int) -> None:
        if address == cv100.CONTROL_WORD_1:
            self._control_word_1(value)
        elif address == cv100.CONTROL_WORD_2:
            cw = cv100.ControlWord2.decode(value)
            if cw.enable and not self.fault_code:
                self.operation_disabled = cw.operation_disable
                self.aux_reference = cw.aux_reference
                if cw.run:
                    self.run, self.reverse, self.jog = True, False, None
        elif address in (cv100.ACCEL_TIME_SETTING, cv100.DECEL_TIME_SETTING):
            code = A0_06 if address == cv100.ACCEL_TIME_SETTING else A0_07
            self.store.holding_registers.set(code, value)
            self.eeprom[code] = value

    def _control_word_1(self, value: int) -> None:
        if self.command_source != 2 or not value & cv100.CW1_ENABLE:
            return
        cw = cv100.ControlWord1.decode(value)
        if cw.fault_reset and self.fault_code:
            self.fault_code = 0
        if self.fault_code:
            return
        self.main_reference = cw.main_reference
        if not cw.acc_dec_enable:
            return
        if cw.jog_forward or cw.jog_reverse:
            if not (cw.jog_forward and cw.jog_reverse):
                self.jog = "forward" if cw.jog_forward else "reverse"
            return
        self.jog = None
        if cw.command is cv100.Command.RUN:
            self.run, self.reverse = True, cw.reverse
        elif cw.command is cv100.Command.STOP:
            self.run = False
        elif cw.command in (cv100.Command.COAST_STOP, cv100.Command.EXTERNAL_FAULT_STOP):
            self.run = False
            self.motor.coast()
            if cw.command is cv100.Command.EXTERNAL_FAULT_STOP:
                self._fault(FAULT_EXTERNAL)

    def _fault(self, code: int) -> None:
        self.fault_code = code
        self.fault_log.append(code)
        self.run, self.jog = False, None
        self.motor.coast()

    # -- the drive ------------------------------------------------------------------------

    def reference_hz(self) -> float:
        if self.main_reference:
            return self._raw(cv100.MAIN_SETTING) / cv100.FREQUENCY_SCALE
        return self.preset_hz

    def _retarget(self) -> None:
        m = self.motor
        m.set_ramp_times(self.max_hz, self._raw(A0_06) / 10, self._raw(A0_07) / 10)
        if self.fault_code or self.operation_disabled or self.undervoltage:
            m.reference = 0.0
            m.coast()
        elif self.jog is not None:
            m.reference = self.jog_hz if self.jog == "forward" else -self.jog_hz
        elif self.run:
            hz = min(self.reference_hz(), self.max_hz)
            m.reference = -hz if self.reverse else hz
        else:
            m.reference = 0.0

    def _on_read_status(self, address: int, count: int) -> None:
        self.update()

    def _refresh(self) -> None:
        self._status.show(self._status_inputs())

    def _status_inputs(self) -> _StatusInputs:
        m, log = self.motor, self.fault_log
        return _StatusInputs(
            m.frequency,
            m.reference,
            self.run,
            self.jog,
            self.reverse,
            self.main_reference,
            self.reference_hz(),
            self.command_source,
            self.fault_code,
            self.alarm_code,
            self.undervoltage,
            log[0] if log else 0,
            log[1] if len(log) > 1 else 0,
            log[-1] if log else 0,
            self.max_hz,
            self.rated_current,
            self._raw(A0_06),
            self._raw(A0_07),
        )

    def _on_telegram(self, now: float, unit: int, pdu: bytes) -> None:
        super()._on_telegram(now, unit, pdu)
        if now <= self._user_until:
            self._user_until = now + ACCESS_SECONDS
        if now <= self._factory_until:
            self._factory_until = now + ACCESS_SECONDS

    # -- the owner's controls ----------------------------------------------------------------

    def power_cycle(self) -> None:
        """Mains off and on: function codes from the EEPROM, control parameters
        cleared (except the saved ones), motor stopped, access rights gone."""
        with self.lock:
            self.update()
            regs = self.store.holding_registers
            for a, v in self.eeprom.items():
                regs.set(a, v)
            for start, n in _CONTROL_RANGES:
                for a in range(start, start + n):
                    if a not in cv100.CONTROL_SAVED:
                        regs.set(a, 0)
            self.run, self.jog, self.main_reference = False, None, False
            self.operation_disabled = False
            self._user_until = self._factory_until = -1.0
            self.motor.frequency = 0.0
            self._retarget()
            self._refresh()

    def inject_fault(self, code: int) -> None:
        with self.lock:
            self.update()
            self._fault(code)
            self._refresh()

    def status(self) -> cv100.CV100Status:
        with self.lock:
            self.update()
            regs = self.store.holding_registers
            return cv100.CV100Status(
                cv100.StatusWord1.decode(int(regs.get(cv100.STATUS_WORD_1))),
                cv100.flags(int(regs.get(cv100.STATUS_WORD_2)), cv100.STATUS_2_BITS),
                cv100.flags(int(regs.get(cv100.STATUS_WORD_3)), cv100.STATUS_3_BITS),
            )

    # -- the slave ------------------------------------------------------------------------

    def slave_options(self) -> dict[str, Any]:
        return {
            "functions": {0x03, 0x06, 0x08, 0x10, 0x41, 0x42, 0x43},
            "mode": self.mode,
            "rules": dict(CV100_RULES),
            "response_delay": 0.001 if self.mode == "ascii" else 0.0,
        }

    def handlers(self) -> dict[int, HandlerSpec]:
        req41, resp41 = CV100_RULES[0x41]
        req42, resp42 = CV100_RULES[0x42]
        req43, resp43 = CV100_RULES[0x43]
        return {
            0x06: (self._write_single, None, None, True),
            0x41: (self._write_single, req41, resp41, True),
            0x10: (self._write_multiple, None, None, True),
            0x43: (self._write_multiple, req43, resp43, True),
            0x42: (self._manage, req42, resp42, False),
        }

    def _write_single(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        address, value = pdus.decode_write_single(pdu)
        self._write(address, [value], pdu[0] == cv100.FC_WRITE_SAVE)
        return pdu

    def _write_multiple(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        address, words = pdus.decode_write_registers(pdu)
        self._write(address, list(words), pdu[0] == cv100.FC_WRITE_MULTIPLE_SAVE)
        return pdu[:5]

    def _write(self, address: int, values: list[int], save: bool) -> None:
        regs = self.store.holding_registers
        self._saving = save
        try:
            if address >> 8 == cv100.CONTROL_GROUP:
                for i, v in enumerate(values):  # the ones before a bad one stay written
                    regs.write(address + i, [v])
            else:
                regs.write(address, list(values))
        finally:
            self._saving = False

    def _manage(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        if len(pdu) != 5:
            raise SlaveException(3, "0x42 carries a sub-function and a data word")
        sub, data = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        if sub in (cv100.Manage.UPPER_LIMIT, cv100.Manage.LOWER_LIMIT, cv100.Manage.FACTORY_VALUE):
            if data >> 8 not in cv100.GROUPS.values() or data & 0xFF >= GROUP_SIZE:
                raise SlaveException(2, f"0x{data:04X} is not a function code")
            self.update()
            self._check_access(data, False)
            code = KNOWN.get(data, Code(""))
            value = {0: code.high, 1: code.low, 2: code.default}[sub]
        elif sub == cv100.Manage.DISPLAY_ADDRESS:
            value = self.display
        elif sub == cv100.Manage.SWITCH_DISPLAY:
            if not _STATUS_FIRST <= data <= _STATUS_LAST:
                raise SlaveException(2, f"0x{data:04X} is not a status parameter")
            self.display = value = data
        else:
            raise SlaveException(1, f"0x42 sub-function 0x{sub:04X} is not supported")
        return pdu[:3] + value.to_bytes(2, "big")
