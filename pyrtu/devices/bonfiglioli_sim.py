"""Simulated Bonfiglioli Vectron ACT / ACU on `pyrtu.Slave`, RTU or ASCII (seed 004).

What the manual gives, and the simulator does:

* FC 03/06 (one 16-bit parameter; No. of Registers other than 1 -> exception 2),
  FC 100/101 (one 32-bit parameter), FC 08 sub-functions 0x0A-0x12 only (others ->
  exception 1, a data field other than 0 -> 3); any other function -> exception 1;
* data-set/parameter addressing: parameters with four data sets (written through
  data set 0 into all four; read through data set 0 only when all four agree, else
  exception 4 with error 9), data sets 5-9 write the RAM only (`power_cycle`, or
  Programming 34 = 123, restores the EEPROM values);
* a failed parameter access answers exception 4 and leaves the reason in the VABus
  SST Error Register 11 (1 value out of range, 2 data set, 3 write-only, 4 read
  only, 8 not while running, 9 data sets differ, 11 unknown parameter), cleared by
  reading it; a data type mismatch (FC 03 on a long parameter...) is exception 3;
* the parameter list of chapter 11 (`bonfiglioli.PARAMETERS`): ranges, read-only
  actual values; on the ACU, Reference Frequency/Percentage RAM 484/524 are
  write only (10.2.3);
* the DRIVECOM state machine with Local/Remote 412 = 1 (the default here): control
  word 410, status word 411 (0x40 -> 0x21 -> 0x23 -> 0x27, quick stop 0x07 along
  the emergency ramps 424/425, transition 5 per State-transition 5 392 with the
  switch-off threshold 637 and holding time 638, fault 0x08, reset on a positive
  edge of bit 7 no sooner than 15 s after the fault); Local/Remote 412 = 2 takes
  bits 0-2 as the contacts S1IND (release), S2IND (start clockwise), S3IND (start
  anticlockwise); 412 = 0 ignores the control word;
* the reference line value 484 (+ the internal reference, 0 Hz here; Ramp Setpoint
  434), limited to the maximum frequency 419, along the ramps 420/421 (Hz/s);
* the watchdog 413 (s) from the first valid telegram -> fault F2010 (Current Error
  260 = 0x2010);
* the response 10 ms after the request at the earliest (6.8).

Choices where the manual is silent: the hardware release (S1IND/STOA+STOB) and the
start contact are wired (``release=True``), so status bit 9 "remote" follows 412;
the ACU's status bit 4 shows the mains voltage (on); "limit value reached" (bit 11)
is set while the reference is limited by the maximum frequency.
"""

from __future__ import annotations

from typing import Any

from pyrtu.core.rules import BONFIGLIOLI as RULES
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import SlaveException

from . import bonfiglioli
from ._simbase import DriveSimulator, HandlerSpec
from .bonfiglioli import DriveState, Parameter, Type, VabusError
from .common import s16, s32
from .motor import Clock, monotonic

FAULT_LOCK_TIME = 15.0
RESPONSE_DELAY = 0.010


class ParameterError(Exception):
    def __init__(self, exception: int, error: VabusError) -> None:
        super().__init__(f"exception {exception}: {error.name}")
        self.exception = exception
        self.error = error


class VectronSimulator(DriveSimulator):
    """``VectronSimulator("ACT")`` or ``("ACU")`` (or `ACTSimulator`/`ACUSimulator`)."""

    model = "ACT"
    device = "act"
    example_addresses = frozenset({1, 3})
    modes = ("rtu", "ascii")

    def __init__(
        self,
        model: str | None = None,
        *,
        mode: str = "rtu",
        release: bool = True,
        fault_lock_time: float = FAULT_LOCK_TIME,
        clock: Clock = monotonic,
    ) -> None:
        super().__init__(mode=mode, clock=clock)
        if model is not None:
            self.model = model.upper()
            self.device = self.model.lower()
        if self.model not in ("ACT", "ACU"):
            raise ValueError("model is 'ACT' or 'ACU'")
        self.release = release
        self.fault_lock_time = fault_lock_time
        self.ram: dict[int, list[int]] = {
            p.number: [p.default] * (4 if p.data_sets else 1)
            for p in bonfiglioli.PARAMETERS.values()
        }
        self.eeprom = {k: list(v) for k, v in self.ram.items()}
        self.state = DriveState.STARTING_LOCKOUT
        self.error_register = VabusError.NO_ERROR
        self.current_error = 0
        self.warnings = 0
        self.fault_time = 0.0
        self.stopping: DriveState | None = None  # target of a timed transition (5, quick stop)
        self.stop_reached: float | None = None  # when the output fell below the threshold
        self.limited = False
        self.eeprom_writes = 0

    # -- values -----------------------------------------------------------------------------

    def _active_set(self) -> int:
        sel = self.ram[bonfiglioli.P_DATA_SET_SELECTION][0]
        return sel if sel else 1

    def value(self, number: int) -> int:
        """A parameter's present value (the active data set's for four-valued ones)."""
        values = self.ram[number]
        return values[self._active_set() - 1] if len(values) == 4 else values[0]

    def _running(self) -> bool:
        return (
            self.state in (DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP)
            or self.motor.frequency != 0
        )

    # -- parameter access (the handlers' core) -------------------------------------------------

    def _lookup(self, start: int, size: int) -> tuple[Parameter, int, bool]:
        data_set, number = bonfiglioli.split(start)
        par = bonfiglioli.PARAMETERS.get(number)
        if par is None:
            raise ParameterError(4, VabusError.UNKNOWN_PARAMETER)
        if par.type.size != size:
            raise ParameterError(3, VabusError.SIZE_MISMATCH)
        ram = data_set >= bonfiglioli.RAM_OFFSET
        ds = data_set - bonfiglioli.RAM_OFFSET if ram else data_set
        if data_set > bonfiglioli.MAX_DATA_SET or (ds != 0 and not par.data_sets):
            raise ParameterError(4, VabusError.INADMISSIBLE_DATA_SET)
        return par, ds, ram

    def read_parameter(self, start: int, size: int) -> int:
        """The raw value of a parameter at ``start`` (data set in the top 4 bits) read
        with ``size`` bytes (2: FC 03, 4: FC 100); `ParameterError` on failure."""
        with self.lock:
            self.update()
            try:
                par, ds, _ = self._lookup(start, size)
                if not par.readable or (self.model == "ACU" and par.number in (484, 524)):
                    raise ParameterError(4, VabusError.NOT_READABLE)
                if par.number == bonfiglioli.P_ERROR_REGISTER:  # cleared by reading it
                    value, self.error_register = int(self.error_register), VabusError.NO_ERROR
                    return value
                values = self.ram[par.number]
                if ds == 0 and len(values) == 4 and len(set(values)) != 1:
                    raise ParameterError(4, VabusError.DATA_SETS_DIFFER)
                return values[ds - 1] if ds else values[0]
            except ParameterError as exc:
                self.error_register = exc.error
                raise

    def write_parameter(self, start: int, raw: int, size: int) -> None:
        """Write a parameter as FC 06 (size 2) or FC 101 (size 4) would."""
        with self.lock:
            self.update()
            try:
                par, ds, ram = self._lookup(start, size)
                if not par.writable:
                    raise ParameterError(4, VabusError.NOT_WRITABLE)
                value = raw if par.type is Type.UINT else s16(raw) if size == 2 else s32(raw)
                if not par.low <= value <= par.high:
                    raise ParameterError(4, VabusError.INADMISSIBLE_VALUE)
                if par.stopped_only and self._running():
                    raise ParameterError(4, VabusError.NOT_WHILE_RUNNING)
            except ParameterError as exc:
                self.error_register = exc.error
                raise
            values = self.ram[par.number]
            previous = values[0]
            sets = range(len(values)) if ds == 0 else [ds - 1]
            for i in sets:
                values[i] = value
                if not ram and not par.ram_only:
                    self.eeprom[par.number][i] = value
                    self.eeprom_writes += 1
            self._written(par.number, value, previous)

    def _written(self, number: int, value: int, previous: int) -> None:
        if number == bonfiglioli.P_CONTROL_WORD:
            self._control_word(value, previous)
        elif number == bonfiglioli.P_WATCHDOG:
            self.supervision.timeout = float(value)
        elif number == bonfiglioli.P_PROGRAMMING and value == 123:
            self.power_cycle()
            return
        elif number == bonfiglioli.P_MODBUS_ADDRESS and self.slave is not None:
            self.slave.addresses = frozenset({value})
        self._retarget()

    def _served_at(self, address: int) -> None:
        super()._served_at(address)
        self.ram[bonfiglioli.P_MODBUS_ADDRESS] = [address]
        self.eeprom[bonfiglioli.P_MODBUS_ADDRESS] = [address]

    # -- the state machine -----------------------------------------------------------------------

    def _control_word(self, word: int, previous: int) -> None:
        now = self.timeline.now
        edge = word & bonfiglioli.CW_FAULT_RESET and not previous & bonfiglioli.CW_FAULT_RESET
        if self.state is DriveState.FAULT:
            if edge and now - self.fault_time >= self.fault_lock_time:
                self.state, self.current_error = DriveState.STARTING_LOCKOUT, 0
                self.supervision.tripped = False
            return
        mode = self.value(bonfiglioli.P_LOCAL_REMOTE)
        if not self.release or mode not in (1, 2):
            return
        if mode == 2:  # remote contacts: S1IND release, S2IND/S3IND start
            start = bool(word & 0x6)
            self.stopping = None
            self.state = (
                DriveState.OPERATION_ENABLED
                if word & 1 and start
                else DriveState.SWITCHED_ON
                if word & 1
                else DriveState.STARTING_LOCKOUT
            )
            return
        if self.stopping is DriveState.SWITCHED_ON and word & 0x0F == 0x0F:
            self.stopping = None  # back to the reference while ramping down (392 = 2)
            return
        target, transition = bonfiglioli.next_state(self.state, word)
        if transition is None:
            return
        if transition == 5:
            how = self.value(bonfiglioli.P_STATE_TRANSITION_5)
            if how == 0:
                self.state = target
                self.motor.coast()
            else:
                self.stopping, self.stop_reached = target, None
                if how == 1:  # DC brake: output off, state changes after the braking time
                    self.motor.coast()
                    self.stop_reached = now - self.value(638) / 10 + self.value(632) / 10
            return
        self.stopping = None
        self.state = target
        if target is DriveState.QUICK_STOP:
            self.stop_reached = None
        elif target is not DriveState.OPERATION_ENABLED:
            self.motor.coast()

    def _line_value(self) -> float:
        return self.ram[bonfiglioli.P_REFERENCE_FREQUENCY][0] / 100

    def _retarget(self) -> None:
        m = self.motor
        fmax = self.value(bonfiglioli.P_MAX_FREQUENCY) / 100
        if self.state is DriveState.QUICK_STOP:
            rate = (
                self.value(
                    bonfiglioli.P_EMERGENCY_CW if m.frequency >= 0 else bonfiglioli.P_EMERGENCY_ACW
                )
                / 100
            )
            m.accel = m.decel = rate
            m.reference = 0.0
            return
        m.accel = self.value(bonfiglioli.P_ACCELERATION) / 100
        m.decel = self.value(bonfiglioli.P_DECELERATION) / 100
        if self.state is not DriveState.OPERATION_ENABLED or self.stopping is not None:
            m.reference = 0.0
            if self.state is not DriveState.OPERATION_ENABLED:
                m.coast()
            return
        setpoint = self.value(bonfiglioli.P_RAMP_SETPOINT)
        line = self._line_value() if setpoint in (2, 3) else 0.0
        if setpoint == 2 and abs(line) < self.value(bonfiglioli.P_MIN_FREQUENCY) / 100:
            line = self.value(bonfiglioli.P_MIN_FREQUENCY) / 100 * (-1 if line < 0 else 1)
        if (
            self.value(bonfiglioli.P_LOCAL_REMOTE) == 2
            and self.ram[bonfiglioli.P_CONTROL_WORD][0] & 0x4
        ):
            line = -abs(line) if not self.ram[bonfiglioli.P_CONTROL_WORD][0] & 0x2 else line
        self.limited = abs(line) > fmax
        m.reference = max(-fmax, min(fmax, line))

    def status_word(self) -> int:
        word = int(self.state)
        if self.model == "ACU":
            word |= 0x10  # voltage enabled: mains on
        if self.warnings:
            word |= 0x80
        if self.release and self.value(bonfiglioli.P_LOCAL_REMOTE) in (1, 2):
            word |= 0x200
        m = self.motor
        tolerance = (
            self.value(bonfiglioli.P_MAX_CONTROL_DEVIATION)
            / 10000
            * self.value(bonfiglioli.P_MAX_FREQUENCY)
            / 100
        )
        if (
            self.state is DriveState.OPERATION_ENABLED
            and abs(m.frequency - m.reference) <= tolerance
        ):
            word |= 0x400
        if self.limited and self.state is DriveState.OPERATION_ENABLED:
            word |= 0x800
        return word

    # -- time ------------------------------------------------------------------------------------

    def _threshold(self) -> float:
        return (
            self.value(bonfiglioli.P_SWITCH_OFF_THRESHOLD)
            / 1000
            * self.value(bonfiglioli.P_MAX_FREQUENCY)
            / 100
        )

    def _stop_target(self) -> DriveState | None:
        if self.state is DriveState.QUICK_STOP:
            return DriveState.STARTING_LOCKOUT
        return self.stopping

    def _next_event(self) -> float | None:
        times = [t for t in (self.supervision.deadline(),) if t is not None]
        if self._stop_target() is not None:
            if self.stop_reached is None:
                thr = self._threshold()
                below = abs(self.motor.frequency) <= thr + 1e-9
                times.append(self.timeline.now + (0.0 if below else self.motor.time_to(thr)))
            else:
                times.append(self.stop_reached + self.value(bonfiglioli.P_HOLDING_TIME) / 10)
        return min(times) if times else None

    def _fire(self, at: float) -> None:
        super()._fire(at)
        target = self._stop_target()
        if target is None:
            return
        if self.stop_reached is None:
            if abs(self.motor.frequency) <= self._threshold() + 1e-9:
                self.stop_reached = at
        elif at >= self.stop_reached + self.value(bonfiglioli.P_HOLDING_TIME) / 10:
            self.state, self.stopping, self.stop_reached = target, None, None
            self.motor.coast()
            self._retarget()

    def _trip(self, at: float) -> None:
        super()._trip(at)
        self.fault(bonfiglioli.F2010, at)

    def fault(self, code: int, at: float | None = None) -> None:
        """A fault (Current Error 260 = ``code``): fault reaction, then state 0x08."""
        with self.lock:
            self.state = DriveState.FAULT
            self.stopping = None
            self.current_error = code
            self.fault_time = self.timeline.now if at is None else at
            self.motor.coast()
            self._retarget()

    def _refresh(self) -> None:
        """The actual values (status word, frequencies, errors) into the parameters."""
        ram, m = self.ram, self.motor
        frequency = round(m.frequency * 100)
        remote_contacts = self.value(bonfiglioli.P_LOCAL_REMOTE) == 2
        values = {
            bonfiglioli.P_ERROR_REGISTER: int(self.error_register),
            bonfiglioli.P_STATOR_FREQUENCY: frequency,
            228: ram[228][0],  # as stored
            229: ram[229][0],
            bonfiglioli.P_ACTUAL_FREQUENCY: frequency,
            bonfiglioli.P_ACTIVE_DATA_SET: self._active_set(),
            250: ram[bonfiglioli.P_CONTROL_WORD][0] & 0xFF
            if remote_contacts
            else 0,  # digital inputs
            bonfiglioli.P_CURRENT_ERROR: self.current_error,
            bonfiglioli.P_WARNINGS: self.warnings,
            282: round(self._line_value() * 100),
            283: round(m.reference * 100),
            bonfiglioli.P_STATUS_WORD: self.status_word(),
        }
        for number, value in values.items():
            ram[number] = [value]

    def power_cycle(self) -> None:
        """Mains off/on (or Programming 34 = 123): RAM values from the EEPROM, state
        machine in starting lock-out, watchdog waiting for the first telegram."""
        with self.lock:
            self.ram = {k: list(v) for k, v in self.eeprom.items()}
            self.ram[bonfiglioli.P_CONTROL_WORD] = [0]
            self.ram[bonfiglioli.P_REFERENCE_FREQUENCY] = [0]
            self.ram[bonfiglioli.P_REFERENCE_PERCENTAGE] = [0]
            self.state, self.stopping, self.current_error = DriveState.STARTING_LOCKOUT, None, 0
            self.motor.frequency = 0.0
            self.supervision.reset()
            self.supervision.timeout = float(self.value(bonfiglioli.P_WATCHDOG))
            self._retarget()

    def status(self) -> bonfiglioli.VectronStatus:
        with self.lock:
            self.update()
            return bonfiglioli.VectronStatus.decode(self.status_word())

    # -- the slave --------------------------------------------------------------------------------

    def slave_options(self) -> dict[str, Any]:
        return {
            "functions": {3, 6, 8, 100, 101},
            "mode": self.mode,
            "rules": dict(RULES),
            "response_delay": RESPONSE_DELAY,
        }

    def handlers(self) -> dict[int, HandlerSpec]:
        (r100, s100), (r101, s101) = RULES[bonfiglioli.FC_READ_32], RULES[bonfiglioli.FC_WRITE_32]
        return {
            3: (self._fc03, None, None, False),
            6: (self._fc06, None, None, True),  # "All devices must accept the broadcast
            8: (self._fc08, None, None, False),  # for writing function" (6.1)
            bonfiglioli.FC_READ_32: (self._fc100, r100, s100, False),
            bonfiglioli.FC_WRITE_32: (self._fc101, r101, s101, True),
        }

    @staticmethod
    def _length(pdu: bytes, n: int) -> None:
        if len(pdu) != n:
            raise SlaveException(
                3, f"function {pdu[0]}: {len(pdu) - 1} data bytes, expected {n - 1}"
            )

    def _call(self, fn: Any, *args: int) -> Any:
        try:
            return fn(*args)
        except ParameterError as exc:
            raise SlaveException(exc.exception, str(exc)) from None

    def _fc03(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        self._length(pdu, 5)
        if int.from_bytes(pdu[3:5], "big") != 1:
            raise SlaveException(2, "No. of Registers must be 1")
        value = self._call(self.read_parameter, int.from_bytes(pdu[1:3], "big"), 2)
        return b"\x03\x02" + (int(value) & 0xFFFF).to_bytes(2, "big")

    def _fc06(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        return self._write(pdu, 2)

    def _fc100(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        self._length(pdu, 3)
        value = self._call(self.read_parameter, int.from_bytes(pdu[1:3], "big"), 4)
        return bytes([bonfiglioli.FC_READ_32]) + (int(value) & 0xFFFFFFFF).to_bytes(4, "big")

    def _fc101(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        return self._write(pdu, 4)

    def _write(self, pdu: bytes, width: int) -> bytes:
        """FC 6 (``width`` 2) or 101 (4): the parameter, then the value; the echo."""
        self._length(pdu, 3 + width)
        self._call(
            self.write_parameter,
            int.from_bytes(pdu[1:3], "big"),
            int.from_bytes(pdu[3 : 3 + width], "big"),
            width,
        )
        return pdu

    def _fc08(self, slave: Slave, unit: int, pdu: bytes) -> bytes | None:
        self._length(pdu, 5)
        sub = int.from_bytes(pdu[1:3], "big")
        if sub != bonfiglioli.CLEAR_COUNTERS and sub not in bonfiglioli.DIAGNOSTIC_COUNTERS:
            raise SlaveException(1, f"diagnostics sub-function 0x{sub:02X} is not supported")
        return slave.line.diagnostics(pdu)


class ACTSimulator(VectronSimulator):
    model = "ACT"
    device = "act"


class ACUSimulator(VectronSimulator):
    model = "ACU"
    device = "acu"
