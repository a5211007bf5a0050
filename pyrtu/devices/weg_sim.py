"""Simulated WEG CFW100 / CFW320 / CFW701 on `pyrtu.Slave`.

What the manuals give, and the simulator does:

* only the model's function codes (CFW100: 03/04/06/16/43; CFW320: 01/02/03/05/06/
  15/16/22/23/43; CFW701: 01-06/15/16/43); others -> exception 1;
* parameters as holding registers at their numbers; a parameter the drive does not
  have -> exception 2 (P2900 in the manual's example); a read-only parameter or a
  value out of range, or a CFG parameter while the motor runs -> exception 3;
* telegrams of at most 64 bytes: a longer request is no telegram (``max_adu=64``: no
  answer), a read whose answer would be longer (FC 03/04/23, more than 29
  registers) -> exception 3;
* FC 43: vendor "WEG", product code ("CFW100"...), revision 'V1.00'; read codes 01/04;
* a response 2 ms after the request (the manual: 2 to 10 ms);
* P680/P681/P682/P683 with the motor model: the reference on the 13-bit scale,
  direction from its sign and control bit 2, ramps P100/P101 (second ramp P102/P103,
  bit 5) from 0 to the maximum frequency P134, general enable, JOG (P122), LOC/REM;
* the watchdog P314 from the first valid telegram: A128 and the P313 action, or
  F228 with P313 = 5; P316 = 2; the alarm clears once telegrams arrive again
  (the first telegram after the timeout still sees it), a fault needs a reset (bit 7).

Choices where the manuals are silent: the drive behaves as programmed for the serial
interface in Remote (P220-P228 are stored, not interpreted) and for the keypad in
Local (which holds no run command unless P313 = 4 kept the network's); the motor
current is P401 x |f| / P403; the CFW701's fast stop (bit 6) ramps down in the fast
stop time P107; P308 shows the address the slave serves; FC 04 reads the same
parameters as FC 03; the SoftPLC bit markers are coils 0-63 (FC 01/05/15),
readable as discrete inputs 0-63 (FC 02).  The default state is the manual's: the
CFW100 runs forward at 30 Hz (P683 = 4096 of P403 = 60 Hz, P002 = 30, P003 = 1.5 A);
the CFW320/CFW701 are stopped.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, NamedTuple

from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import SlaveException

from .. import pdu as pdus
from . import weg
from ._simbase import DriveSimulator, HandlerSpec, Outputs
from .motor import Clock, monotonic
from .weg import ErrorAction, InterfaceStatus, WegModel, WegParam

MARKERS = 64
RESPONSE_DELAY = 0.002


def _runs(params: dict[int, WegParam]) -> list[tuple[int, list[WegParam]]]:
    """Consecutive parameters with the same read-only property."""
    runs: list[tuple[int, list[WegParam]]] = []
    for number in sorted(params):
        p = params[number]
        if runs and runs[-1][0] + len(runs[-1][1]) == number and runs[-1][1][-1].ro == p.ro:
            runs[-1][1].append(p)
        else:
            runs.append((number, [p]))
    return runs


class _OutputInputs(NamedTuple):
    """Everything the output parameters (P001-P007, P048/P049, P316, P680/P681) are
    computed from."""

    commands: tuple[bool, bool, bool, bool, bool, int, bool]  # `WegSimulator._commands`
    frequency: float  # the motor's, signed Hz
    reference: float
    rated_hz: float  # P403
    rated_current: int  # P401, raw
    fault_code: int
    alarm_code: int
    undervoltage: bool
    config_mode: bool
    fire_mode: bool
    watchdog_tripped: bool
    seen_traffic: bool
    model: str


def _status(s: _OutputInputs) -> weg.WegStatus:
    """P680, from ``s`` alone."""
    remote, run, enable, jog, ramp2, ref, dirbit = s.commands
    f = s.frequency
    enabled = enable and not (bool(s.fault_code) or s.undervoltage or s.config_mode)
    running = enabled and (f != 0.0 or run or jog)
    forward = f > 0 if f != 0.0 else weg.reference_direction(4 if dirbit else 0, ref)
    cfw320 = s.model == "CFW320"
    return weg.WegStatus(
        0,
        second_ramp=ramp2,
        config_mode=s.config_mode,
        alarm=s.alarm_code != 0,
        running=running,
        enabled=enabled,
        forward=forward,
        jog=enabled and jog and not run,
        remote=remote,
        undervoltage=s.undervoltage,
        fault=s.fault_code != 0,
        run_command=run if cfw320 else None,
        fire_mode=s.fire_mode if cfw320 else None,
    )


def _output_parameters(s: _OutputInputs) -> dict[int, int]:
    """The output parameters' values (number -> value), from ``s`` alone."""
    f = s.frequency
    rated = s.rated_hz
    st = _status(s)
    current = round(s.rated_current * abs(f) / rated) if rated else 0
    state = (
        3 if st.fault else 2 if st.undervoltage else 5 if st.config_mode else 1 if st.running else 0
    )
    if s.watchdog_tripped:
        interface = InterfaceStatus.WATCHDOG_ERROR
    else:
        interface = InterfaceStatus.ACTIVE if s.seen_traffic else InterfaceStatus.INACTIVE
    return {
        1: round(abs(s.reference) * 10),
        2: round(abs(f)),
        3: current,
        4: 200 if s.undervoltage else 311,
        5: round(abs(f) * 10),
        6: state,
        7: round(220 * abs(f) / rated) if rated else 0,
        weg.P_PRESENT_ALARM: s.alarm_code,
        weg.P_PRESENT_FAULT: s.fault_code,
        weg.P_STATUS: weg.encode_status(st, s.model),
        weg.P_SPEED: weg.hz_to_13bit(f, rated) & 0xFFFF if rated else 0,
        weg.P_INTERFACE_STATUS: int(interface),
    }


class WegSimulator(DriveSimulator):
    """A WEG drive: ``WegSimulator("CFW701")`` (or `CFW100Simulator`...).

    ``state``: ``"manual"`` (the default: the state of the manual's examples) or
    ``"stopped"``.  ``clock``: seconds, monotonic (inject a `ManualClock` in tests).
    """

    model: WegModel = weg.CFW701_MODEL
    device = "cfw701"

    def __init__(
        self,
        model: str | None = None,
        *,
        state: str = "manual",
        mode: str = "rtu",
        clock: Clock = monotonic,
    ) -> None:
        super().__init__(mode=mode, clock=clock)
        if model is not None:
            self.model = weg.MODELS[model.upper()]
            self.device = self.model.name.lower()
        if state not in ("manual", "stopped"):
            raise ValueError("state is 'manual' or 'stopped'")
        self.params = weg.parameters(self.model)
        self.fault_code = 0
        self.alarm_code = 0
        self.undervoltage = False
        self.config_mode = False
        self.fire_mode = False
        # the keypad's commands, used in Local
        self.local_run = False
        self.local_enable = True
        self.local_jog = False
        self.local_forward = True
        self.local_reference = 0
        self._seen_traffic = self.model.name != "CFW320"
        self._recovering = False
        #: the output parameters (P001-P007, P048/P049, P316, P680/P681), shown by
        #: `_refresh`
        self._outputs = Outputs(self.store.holding_registers, _output_parameters)
        regs = self.store.holding_registers
        for start, run in _runs(self.params):
            values = [p.default & 0xFFFF for p in run]
            regs.add_range(
                start,
                values,
                read_only=run[0].ro,
                validator=self._validate,
                on_write=self._on_write,
                on_read=self._on_read,
            )
            if 4 in self.model.functions:
                self.store.input_registers.add_range(
                    start, values, read_only=True, on_read=self._on_read_input
                )
        if {1, 2, 5, 15} & self.model.functions:
            self.store.coils.add_range(0, [False] * MARKERS)
            self.store.discrete_inputs.add_range(
                0, [False] * MARKERS, on_read=self._on_read_markers
            )
        if state == "manual" and self.model.name == "CFW100":
            regs.set(weg.P_CONTROL, weg.control_word(run=True))
            regs.set(weg.P_REFERENCE, weg.hz_to_13bit(30, 60))
            self.motor.frequency = 30.0
        with self.lock:
            self._retarget()
            self.motor.frequency = self.motor.reference
            self._refresh()

    # -- parameters ---------------------------------------------------------------------

    def get(self, number: int) -> int:
        """A parameter's raw value (the owner's view: no checks)."""
        with self.lock:
            self.update()
            value = self.store.holding_registers.get(number)
            return int(value)

    def set(self, number: int, value: int) -> None:
        """Set a parameter as the drive's keypad would (no serial checks), and act on it."""
        with self.lock:
            self.update()
            self.store.holding_registers.set(number, value & 0xFFFF)
            self._apply([number])

    def _raw(self, number: int) -> int:
        return int(self.store.holding_registers.get(number))

    def _validate(self, address: int, value: int | bool) -> bool:
        p = self.params[address]
        if not p.accepts(int(value)):
            return False
        return not (p.cfg and self.motor.frequency != 0.0)

    def _on_write(self, address: int, values: list[int | bool]) -> None:
        self.update()
        self._apply(range(address, address + len(values)))

    def _apply(self, numbers: Iterable[int]) -> None:
        refs = self.model.reference_registers
        for n in numbers:
            if n in refs and len(refs) > 1:
                for other in refs:
                    if other != n:
                        self.store.holding_registers.set(other, self._raw(n))
            if n == weg.P_CONTROL and self._raw(n) & 0x80 and self.fault_code:
                self.reset_fault()
            if n == weg.P_WATCHDOG:
                self.supervision.timeout = self._raw(n) / 10
        self._retarget()
        self._refresh()

    def _on_read(self, address: int, count: int) -> None:
        self.update()

    def _on_read_input(self, address: int, count: int) -> None:
        self.update()
        for a in range(address, address + count):
            self.store.input_registers.set(a, self.store.holding_registers.get(a))

    def _on_read_markers(self, address: int, count: int) -> None:
        for a in range(address, address + count):
            self.store.discrete_inputs.set(a, self.store.coils.get(a))

    def _served_at(self, address: int) -> None:
        super()._served_at(address)
        self.store.holding_registers.set(weg.P_SERIAL_ADDRESS, address)

    # -- the drive ----------------------------------------------------------------------

    @property
    def rated_hz(self) -> float:
        return float(self._raw(weg.P_RATED_FREQUENCY))

    def _commands(self) -> tuple[bool, bool, bool, bool, bool, int, bool]:
        """(remote, run, enable, jog, second ramp, reference, direction bit)."""
        ctl = self._raw(weg.P_CONTROL)
        if ctl & 0x10:
            return (
                True,
                bool(ctl & 1),
                bool(ctl & 2),
                bool(ctl & 8),
                bool(ctl & 0x20),
                self._raw(weg.P_REFERENCE),
                bool(ctl & 4),
            )
        return (
            False,
            self.local_run,
            self.local_enable,
            self.local_jog,
            False,
            self.local_reference,
            self.local_forward,
        )

    def _blocked(self) -> bool:
        return bool(self.fault_code) or self.undervoltage or self.config_mode

    def _retarget(self) -> None:
        remote, run, enable, jog, ramp2, ref, dirbit = self._commands()
        m = self.motor
        if self._blocked() or not enable:
            m.reference = 0.0
            m.coast()
            return
        fmax = self._raw(weg.P_MAX_FREQUENCY) / 10
        acc, dec = (
            (weg.P_ACCEL_TIME_2, weg.P_DECEL_TIME_2)
            if ramp2
            else (weg.P_ACCEL_TIME, weg.P_DECEL_TIME)
        )
        m.set_ramp_times(fmax, self._raw(acc) / 10, self._raw(dec) / 10)
        forward = weg.reference_direction(4 if dirbit else 0, ref)
        if remote and self.model.name == "CFW701" and self._raw(weg.P_CONTROL) & 0x40:
            m.set_ramp_times(fmax, self._raw(acc) / 10, self._raw(107) / 10)
            m.reference = 0.0
            return
        if run:
            hz = min(abs(weg.hz_from_13bit(ref, self.rated_hz)), fmax)
        elif jog:
            hz = min(self._raw(weg.P_JOG_REFERENCE) / 10, fmax)
        else:
            hz = 0.0
        m.reference = hz if forward else -hz

    def _refresh(self) -> None:
        self._outputs.show(self._output_inputs())

    def _output_inputs(self) -> _OutputInputs:
        return _OutputInputs(
            self._commands(),
            self.motor.frequency,
            self.motor.reference,
            self.rated_hz,
            self._raw(weg.P_RATED_CURRENT),
            self.fault_code,
            self.alarm_code,
            self.undervoltage,
            self.config_mode,
            self.fire_mode,
            self.supervision.tripped,
            self._seen_traffic,
            self.model.name,
        )

    # -- supervision ----------------------------------------------------------------------

    def _trip(self, at: float) -> None:
        super()._trip(at)
        action = ErrorAction(self._raw(weg.P_ERROR_ACTION))
        self._recovering = False
        if action is ErrorAction.CAUSE_FAULT:
            self.fault_code = weg.F228
        else:
            self.alarm_code = weg.A128
            if action is ErrorAction.LOCAL_KEEP_COMMANDS:
                _, run, enable, jog, _, ref, dirbit = self._commands()
                self.local_run, self.local_enable, self.local_jog = run, enable, jog
                self.local_reference, self.local_forward = ref, dirbit
            ctl = self._raw(weg.P_CONTROL)
            self.store.holding_registers.set(weg.P_CONTROL, weg.apply_error_action(ctl, action))
        self._retarget()

    def _on_telegram(self, now: float, unit: int, pdu: bytes) -> None:
        super()._on_telegram(now, unit, pdu)
        self._seen_traffic = True
        if self.supervision.tripped:
            if self._recovering:
                self.supervision.tripped = False
                if self.alarm_code == weg.A128:
                    self.alarm_code = 0
            else:
                self._recovering = True

    # -- the owner's controls ---------------------------------------------------------------

    def reset_fault(self) -> None:
        """What bit 7 of P682 does: clear the fault (and a tripped watchdog)."""
        with self.lock:
            self.fault_code = 0
            if self.supervision.tripped:
                self.supervision.tripped = False
            self._retarget()
            self._refresh()

    def inject_fault(self, code: int) -> None:
        """A drive fault (P049 = ``code``): the motor coasts until a reset."""
        with self._changing():
            self.fault_code = code

    def set_undervoltage(self, on: bool) -> None:
        with self._changing():
            self.undervoltage = on

    @contextmanager
    def _changing(self) -> Iterator[None]:
        """Under the lock: the model brought to now, the caller's change of the drive's
        state, then the motor's reference and the registers following it."""
        with self.lock:
            self.update()
            yield
            self._retarget()
            self._refresh()

    def status(self) -> weg.WegStatus:
        """P680 decoded, now."""
        return weg.decode_status(self.get(weg.P_STATUS), self.model.name)

    def speed_hz(self) -> float:
        """The motor's speed now, in Hz (the drive profile's name; `frequency_hz` too)."""
        return self.frequency_hz()

    # -- the slave ------------------------------------------------------------------------

    def identification(self) -> dict[int, bytes]:
        return {
            0: self.model.vendor.encode(),
            1: self.model.name.encode(),
            2: self.model.firmware.encode(),
        }

    def slave_options(self) -> dict[str, Any]:
        return {
            "functions": set(self.model.functions),
            "identification": self.identification(),
            "max_adu": weg.MAX_TELEGRAM,
            "response_delay": RESPONSE_DELAY,
        }

    def handlers(self) -> dict[int, HandlerSpec]:
        out: dict[int, HandlerSpec] = {43: (self._fc43, None, None, False)}
        for fc in (3, 4, 23):
            if fc in self.model.functions:
                out[fc] = (self._read_limited, None, None, fc == pdus.READ_WRITE_REGISTERS)
        return out

    def _read_limited(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        """FC 03/04/23 within the 64-byte telegram limit: a response that would be
        longer (more than 29 registers) is refused with exception 3."""
        if pdu[0] == pdus.READ_WRITE_REGISTERS:
            raddr, rcount, waddr, words = pdus.decode_read_write(pdu)
        else:
            raddr, rcount = pdus.decode_read(pdu)
        if 5 + 2 * rcount > weg.MAX_TELEGRAM:
            raise SlaveException(3, f"{rcount} registers exceed the 64-byte telegram limit")
        table = (
            self.store.input_registers
            if pdu[0] == pdus.READ_INPUT_REGISTERS
            else self.store.holding_registers
        )
        if pdu[0] == pdus.READ_WRITE_REGISTERS:
            table.check_read(raddr, rcount)
            table.write(waddr, list(words))
        return pdus.registers_response(pdu[0], [int(v) for v in table.read(raddr, rcount)])

    def _fc43(self, slave: Slave, unit: int, pdu: bytes) -> bytes:
        """FC 43 / MEI 14 with read codes 01 (basic, in sequence) and 04 (one object)."""
        if len(pdu) != 4 or pdu[1] != 0x0E:
            raise SlaveException(1 if len(pdu) >= 2 and pdu[1] != 0x0E else 3)
        code, obj = pdu[2], pdu[3]
        objects = self.identification()
        if code not in (1, 4):
            raise SlaveException(3)
        if code == 4:
            if obj not in objects:
                raise SlaveException(2)
            chosen = [obj]
        else:
            start = obj if obj in objects else 0
            chosen = [k for k in sorted(objects) if k >= start]
        body = b"".join(bytes([k, len(objects[k])]) + objects[k] for k in chosen)
        return bytes([0x2B, 0x0E, code, 0x81, 0x00, 0x00, len(chosen)]) + body


class CFW100Simulator(WegSimulator):
    model = weg.CFW100_MODEL
    device = "cfw100"
    example_addresses = frozenset({1, 3, 15})


class CFW320Simulator(WegSimulator):
    model = weg.CFW320_MODEL
    device = "cfw320"


class CFW701Simulator(WegSimulator):
    model = weg.CFW701_MODEL
    device = "cfw701"
