"""Bonfiglioli Vectron ACT / ACU with CM-232 / CM-485 (seed 004).

Addressing: a parameter number (0..1599, low 12 bits) and a data set (0..4, top 4
bits; +5 writes the RAM only, without an EEPROM cycle): parameter 372 in data set 2
is register 0x2174.  FC 03/06 read/write ONE 16-bit parameter (No. of Registers must
be 1); the vendor codes FC 100/101 read/write one 32-bit ("long") parameter; FC 08
returns the diagnostic counters 0x0B..0x12 (0x0A clears them).

Control: `Local/Remote 412` = 1 drives the DRIVECOM state machine with the control
word 410; the status word 411 reports it (bits 0..6: 0x40 starting lock-out, 0x21
ready, 0x23 switched on, 0x27 operation enabled, 0x07 quick stop, 0x08 fault).  The
reference line value is `Reference Frequency RAM 484` (Hz, 2 decimals, 32-bit) or
`Reference Percentage RAM 524`.  After a failed request, `VABus SST Error Register
11` says why (reading it clears it).  Watchdog 413 (s) -> fault F2010.

    drive = ACU(master, address=1)
    drive.set_frequency_hz(30)
    drive.start()          # 0x40 -> 0x21 -> 0x23 -> 0x27 as needed
    drive.state()          # DriveState.OPERATION_ENABLED
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

from pyrtu.core.rules import BONFIGLIOLI

from .common import FlagWord, MasterLike, flag, s16, s32, scaled, u16, u32, unscaled

FC_READ_32 = 100
FC_WRITE_32 = 101
RAM_OFFSET = 5
MAX_PARAMETER = 1599
MAX_DATA_SET = 9

# parameters named in the manual
P_BAUD_RATE = 10
P_ERROR_REGISTER = 11
P_PROGRAMMING = 34
P_STATOR_FREQUENCY = 210
P_ACTUAL_FREQUENCY = 241
P_ACTIVE_DATA_SET = 249
P_CURRENT_ERROR = 260
P_WARNINGS = 270
P_RATED_SPEED = 372
P_RATED_FREQUENCY = 375
P_RATED_POWER = 376
P_STATE_TRANSITION_5 = 392
P_PROTOCOL = 395
P_CONTROL_WORD = 410
P_STATUS_WORD = 411
P_LOCAL_REMOTE = 412
P_WATCHDOG = 413
P_DATA_SET_SELECTION = 414
P_MIN_FREQUENCY = 418
P_MAX_FREQUENCY = 419
P_ACCELERATION = 420
P_DECELERATION = 421
P_EMERGENCY_CW = 424
P_EMERGENCY_ACW = 425
P_RAMP_SETPOINT = 434
P_FIXED_FREQUENCY_2 = 481
P_REFERENCE_FREQUENCY = 484
P_REFERENCE_PERCENTAGE = 524
P_MAX_CONTROL_DEVIATION = 549
P_SWITCH_OFF_THRESHOLD = 637
P_HOLDING_TIME = 638
P_MODBUS_PARITY = 1375
P_MODBUS_ADDRESS = 1376

#: the watchdog fault: error group F20 (communication), code 10
F2010 = 0x2010


def address(parameter: int, data_set: int = 0, *, ram: bool = False) -> int:
    """The start address of a parameter: data set (0..4, +5 for RAM only) in the top
    4 bits, parameter number (0..1599) in the low 12: ``address(372, 2) == 0x2174``."""
    if not 0 <= parameter <= 0xFFF:
        raise ValueError(f"parameter number {parameter} does not fit in 12 bits")
    top = data_set + RAM_OFFSET if ram else data_set
    if not 0 <= data_set <= (4 if ram else MAX_DATA_SET) or top > MAX_DATA_SET:
        raise ValueError(f"data set {data_set} is not 0..4 (RAM: +5, at most 9)")
    return top << 12 | parameter


def split(start_address: int) -> tuple[int, int]:
    """``(data set 0..15, parameter number)`` of a start address."""
    return start_address >> 12 & 0xF, start_address & 0xFFF


# -- the parameter list (chapter 11, plus the examples' and the ramp parameters) --------


class Type(enum.Enum):
    UINT = "uint"  # 16 bit unsigned (FC 03/06)
    INT = "int"  # 16 bit signed (FC 03/06)
    LONG = "long"  # 32 bit signed (FC 100/101)

    @property
    def size(self) -> int:
        return 4 if self is Type.LONG else 2


@dataclass(frozen=True)
class Parameter:
    """One parameter.  Raw values are transmitted without the decimal point."""

    number: int
    name: str
    type: Type
    decimals: int = 0
    low: int = 0
    high: int = 0xFFFF
    default: int = 0
    unit: str = ""
    data_sets: bool = False  # four data values (data sets 1..4)
    readable: bool = True
    writable: bool = True
    stopped_only: bool = False  # "cannot be written when the inverter is in operation"
    ram_only: bool = False  # 410, 484, 524: data set 0, never in the EEPROM
    source: str = "ch. 11"

    def to_raw(self, value: float) -> int:
        return unscaled(value, self.decimals)

    def from_raw(self, raw: int) -> float:
        return scaled(raw, self.decimals)


def _p(
    number: int,
    name: str,
    t: Type,
    decimals: int,
    low: int,
    high: int,
    default: int,
    unit: str = "",
    flags: str = "",
    source: str = "ch. 11",
) -> Parameter:
    """``flags``: ``ds`` four data sets, ``ro`` read only, ``stop`` not while running,
    ``ram`` RAM only (data set 0)."""
    f = set(flags.split())
    return Parameter(number, name, t, decimals, low, high, default, unit, data_sets="ds" in f,
                     writable="ro" not in f, stopped_only="stop" in f, ram_only="ram" in f,
                     source=source)  # fmt: skip


U, L = Type.UINT, Type.LONG
_OI = "operating instructions"
PARAMETERS: Mapping[int, Parameter] = {
    p.number: p
    for p in (
        # 11.1 actual values (read only)
        _p(228, "Internal Reference Frequency", L, 2, -100000, 100000, 0, "Hz", "ro"),
        _p(229, "Reference Percentage Value", L, 2, -30000, 30000, 0, "%", "ro"),
        _p(249, "Active Data Set", U, 0, 1, 4, 1, "", "ro"),
        _p(250, "Digital Inputs", U, 0, 0, 255, 0, "", "ro"),
        _p(260, "Current Error", U, 0, 0, 0xFFFF, 0, "", "ro"),
        _p(270, "Warnings", U, 0, 0, 0xFFFF, 0, "", "ro"),
        _p(282, "Ref. Bus Frequency", L, 2, -100000, 100000, 0, "Hz", "ro"),
        _p(283, "Ref. Ramp Frequency", L, 2, -100000, 100000, 0, "Hz", "ro"),
        _p(411, "Status Word", U, 0, 0, 0xFFFF, 0x40, "", "ro"),
        # 11.2 parameters
        _p(10, "Baud Rate", U, 0, 1, 6, 4),
        _p(11, "VABus SST Error Register", U, 0, 0, 15, 0, "", "ro"),
        _p(34, "Program(ming)", U, 0, 0, 9999, 0),
        _p(392, "State-transition 5", U, 0, 0, 2, 2),
        _p(394, "RS232/RS485 NodeID", U, 0, 1, 30, 1),
        _p(395, "Protocol", U, 0, 0, 3, 2),
        _p(410, "Control Word", U, 0, 0, 0xFFFF, 0, "", "ram"),
        _p(412, "Local/Remote", U, 0, 0, 44, 1, "", "ds"),
        _p(413, "RS232/RS485 Watchdog Timer", U, 0, 0, 10000, 0, "s"),
        _p(414, "Data Set Selection", U, 0, 0, 4, 0),
        _p(424, "Emergency Stop Clockwise", L, 2, 1, 999999, 500, "Hz/s", "ds"),
        _p(425, "Emergency Stop Anticlockwise", L, 2, 1, 999999, 500, "Hz/s", "ds"),
        _p(434, "Ramp Setpoint", U, 0, 1, 3, 3, "", "ds"),
        _p(484, "Reference Frequency RAM", L, 2, -99999, 99999, 0, "Hz", "ram"),
        _p(524, "Reference Percentage RAM", L, 2, -30000, 30000, 0, "%", "ram"),
        _p(549, "Max. Control Deviation", U, 2, 1, 2000, 500, "%", "ds"),
        _p(632, "Braking Time", U, 1, 0, 2000, 100, "s", "ds"),
        _p(637, "Switch-Off Threshold", U, 1, 0, 1000, 10, "%", "ds"),
        _p(638, "Holding Time", U, 1, 0, 2000, 10, "s", "ds"),
        _p(1375, "Modbus Parity", U, 0, 0, 2, 0),
        _p(1376, "Modbus Address", U, 0, 1, 247, 1),
        # the worked examples of chapter 8
        _p(372, "Rated Speed", U, 0, 96, 60000, 1390, "rpm", "ds stop", "ch. 8"),
        _p(375, "Rated Frequency", L, 2, 1000, 100000, 5000, "Hz", "ds stop", "ch. 8"),
        _p(376, "Rated Mech. Power", U, 1, 1, 9999, 11, "kW", "ds stop", "ch. 8"),
        _p(481, "Fixed Frequency 2", L, 2, -99999, 99999, 1000, "Hz", "ds", "ch. 8"),
        # actual values and ramps chapters 9/10 name (ranges from the operating instructions)
        _p(210, "Stator Frequency", L, 2, -100000, 100000, 0, "Hz", "ro", "ch. 9.2.1"),
        _p(241, "Actual Frequency", L, 2, -100000, 100000, 0, "Hz", "ro", "ch. 10.2.3"),
        _p(418, "Minimum Frequency", L, 2, 0, 99999, 350, "Hz", "ds", "ch. 9.2.1"),
        _p(419, "Maximum Frequency", L, 2, 0, 99999, 5000, "Hz", "ds", "ch. 9.1.2.1"),
        _p(420, "Acceleration (Clockwise)", L, 2, 1, 999999, 500, "Hz/s", "ds", _OI),
        _p(421, "Deceleration (Clockwise)", L, 2, 1, 999999, 500, "Hz/s", "ds", _OI),
    )
}


class VabusError(enum.IntEnum):
    """Parameter 11, VABus SST Error Register (section 6.6)."""

    NO_ERROR = 0
    INADMISSIBLE_VALUE = 1
    INADMISSIBLE_DATA_SET = 2
    NOT_READABLE = 3
    NOT_WRITABLE = 4
    EEPROM_READ = 5
    EEPROM_WRITE = 6
    EEPROM_CHECKSUM = 7
    NOT_WHILE_RUNNING = 8
    DATA_SETS_DIFFER = 9
    WRONG_TYPE = 10
    UNKNOWN_PARAMETER = 11
    TELEGRAM_CHECKSUM = 12
    TELEGRAM_SYNTAX = 13
    SIZE_MISMATCH = 14
    UNKNOWN = 15


#: FC 08 sub-functions (section 6.4.5)
DIAGNOSTIC_COUNTERS: Mapping[int, str] = {
    0x0B: "bus_message_count",
    0x0C: "bus_communication_error_count",
    0x0D: "bus_exception_error_count",
    0x0E: "slave_message_count",
    0x0F: "slave_no_response_count",
    0x10: "slave_nak_count",
    0x11: "slave_busy_count",
    0x12: "bus_character_overrun_count",
}
CLEAR_COUNTERS = 0x0A

WARNINGS: Mapping[int, str] = {
    0: "Ixt",
    1: "Short-Term Ixt",
    2: "Long-Term Ixt",
    3: "Heat Sink Temperature Tk",
    4: "Inside Temperature Ti",
    5: "I-limit",
    6: "Init",
    7: "Motor Temperature",
    8: "Phase Failure",
    9: "Motor Protection Switch",
    10: "Fmax",
    11: "Analog Input MFI1A",
    12: "Analog Input A2 (EM-S1INA)",
    13: "System Bus Slave Failure",
    14: "Udc",
    15: "V-belt",
}


def fault_text(code: int) -> str:
    """Current Error 260 as the manual writes it: 0x2010 -> ``"F2010"``."""
    return f"F{code >> 8:02X}{code & 0xFF:02X}"


def warnings_of(word: int) -> list[str]:
    return [name for bit, name in WARNINGS.items() if word >> bit & 1]


# -- DRIVECOM state machine (9.1.2 / 10.2) -------------------------------------------


class DriveState(enum.IntEnum):
    """The state, as status word 411 bits 0..6 (bit 4 ignored) report it."""

    NOT_READY = 0x00
    STARTING_LOCKOUT = 0x40  # "switch on disabled"
    READY = 0x21  # ready for being switched on
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP = 0x07
    FAULT_REACTION = 0x0F
    FAULT = 0x08


STATE_MASK = 0x6F  # bits 0, 1, 2, 3, 5, 6


def state_of(status_word: int) -> DriveState:
    """The DRIVECOM state of a status word (bits 4 and 7..15 ignored)."""
    bits = status_word & STATE_MASK
    if bits & 0x08:
        return DriveState.FAULT_REACTION if bits & 0x07 == 0x07 else DriveState.FAULT
    if bits & 0x40:
        return DriveState.STARTING_LOCKOUT
    for st in (
        DriveState.OPERATION_ENABLED,
        DriveState.SWITCHED_ON,
        DriveState.READY,
        DriveState.QUICK_STOP,
    ):
        if bits == st.value:
            return st
    return DriveState.NOT_READY


# control word 410 bits
CW_SWITCH_ON = 0x01
CW_ENABLE_VOLTAGE = 0x02
CW_QUICK_STOP = 0x04  # 0 = quick stop
CW_ENABLE_OPERATION = 0x08
CW_FAULT_RESET = 0x80
CW_HALT = 0x100  # ACU, motion control configurations


class Command(enum.IntEnum):
    """Control word values of the commands (tables in 9.1.2 and 10.2)."""

    DISABLE_VOLTAGE = 0x00
    QUICK_STOP = 0x02
    SHUTDOWN = 0x06
    SWITCH_ON = 0x07
    DISABLE_OPERATION = 0x07
    ENABLE_OPERATION = 0x0F
    FAULT_RESET = 0x80


def next_state(state: DriveState, word: int) -> tuple[DriveState, int | None]:
    """The state a control word leads to, and the transition number (None: no
    change).  Fault reset (15) needs a positive edge of bit 7 and is not decided here;
    nor are the timed transitions (quick stop and ramped transition 5 end at
    standstill): the caller applies those."""
    voltage = bool(word & CW_ENABLE_VOLTAGE)
    quick = not word & CW_QUICK_STOP
    switch_on = bool(word & CW_SWITCH_ON)
    operate = bool(word & CW_ENABLE_OPERATION)
    if state in (DriveState.FAULT, DriveState.FAULT_REACTION, DriveState.NOT_READY):
        return state, None
    if not voltage:
        table = {
            DriveState.READY: 7,
            DriveState.OPERATION_ENABLED: 9,
            DriveState.SWITCHED_ON: 10,
            DriveState.QUICK_STOP: 12,
        }
        return (DriveState.STARTING_LOCKOUT, table[state]) if state in table else (state, None)
    if quick:
        if state is DriveState.OPERATION_ENABLED:
            return DriveState.QUICK_STOP, 11
        if state in (DriveState.READY, DriveState.SWITCHED_ON):
            return DriveState.STARTING_LOCKOUT, 7 if state is DriveState.READY else 10
        return state, None
    if state is DriveState.QUICK_STOP:
        return state, None
    if not switch_on:  # shutdown: xxx110
        if state is DriveState.STARTING_LOCKOUT:
            return DriveState.READY, 2
        if state is DriveState.SWITCHED_ON:
            return DriveState.READY, 6
        if state is DriveState.OPERATION_ENABLED:
            return DriveState.READY, 8
        return state, None
    if operate:  # enable operation: x1111
        if state in (DriveState.SWITCHED_ON, DriveState.STARTING_LOCKOUT):
            return DriveState.OPERATION_ENABLED, 4  # from 0x40: the manual's extension
        if state is DriveState.READY:
            return DriveState.SWITCHED_ON, 3
        return state, None
    if state is DriveState.READY:  # switch on: xx111
        return DriveState.SWITCHED_ON, 3
    if state is DriveState.OPERATION_ENABLED:  # disable operation: x0111
        return DriveState.SWITCHED_ON, 5
    return state, None


@dataclass(frozen=True)
class VectronStatus(FlagWord):
    """Status word 411 decoded."""

    ready: bool = flag(0)
    switched_on: bool = flag(1)
    operation_enabled: bool = flag(2)
    fault: bool = flag(3)
    voltage: bool = flag(4)  # ACT: "voltage disabled"; ACU: "voltage enabled" (mains on)
    quick_stop: bool = flag(5)  # 1 = no quick stop active (DRIVECOM)
    starting_lockout: bool = flag(6)
    warning: bool = flag(7)
    remote: bool = flag(9)
    reference_reached: bool = flag(10)
    limit_active: bool = flag(11)
    warning2: bool = flag(15)

    @classmethod
    def decode(cls, word: int) -> VectronStatus:
        return cls(word, **cls.flags_in(word))

    @property
    def state(self) -> DriveState:
        return state_of(self.word)

    def describe(self) -> str:
        parts = [self.state.name.lower().replace("_", " ")]
        for name in ("remote", "reference_reached", "limit_active", "warning", "warning2"):
            if getattr(self, name):
                parts.append(name.replace("_", " "))
        return ", ".join(parts)


def describe_register(start_address: int, value: int) -> str | None:
    """For monitors: a parameter value (FC 03/06: 16 bits; FC 100/101: 32 bits) in the
    manual's terms."""
    data_set, number = split(start_address)
    if number == P_STATUS_WORD:
        return f"411 status: {VectronStatus.decode(value).describe()} (0x{value:04X})"
    if number == P_CONTROL_WORD:
        return f"410 control: 0x{value:04X}"
    par = PARAMETERS.get(number)
    if par is None:
        return None
    raw = s16(value) if par.type is Type.INT else s32(value) if par.type is Type.LONG else value
    return f"{number} {par.name} (data set {data_set}): {par.from_raw(raw):g} {par.unit}".rstrip()


# -- profile --------------------------------------------------------------------


class Vectron:
    """A Bonfiglioli Vectron inverter on a bus, seen from the master.  Use `ACT`/`ACU`."""

    model = "ACT"
    actual_frequency = P_STATOR_FREQUENCY

    def __init__(self, master: MasterLike, address: int = 1) -> None:
        self.master = master
        self.address = address
        self._control = 0

    # parameters
    def read_raw(self, parameter: int, data_set: int = 0, *, size: int | None = None) -> int:
        """A parameter's transmitted value (signed for int/long).  ``size``: 2 or 4 bytes
        for parameters outside `PARAMETERS`."""
        par = PARAMETERS.get(parameter)
        nbytes = size or (par.type.size if par else 2)
        start = address(parameter, data_set)
        if nbytes == 4:
            req, resp = BONFIGLIOLI[FC_READ_32]
            data = self.master.execute(
                self.address,
                FC_READ_32,
                start.to_bytes(2, "big"),
                request_rule=req,
                response_rule=resp,
            )
            return s32(int.from_bytes(data[:4], "big"))
        raw = self.master.read_holding_registers(self.address, start, 1)[0]
        return s16(raw) if par is not None and par.type is Type.INT else raw

    def write_raw(
        self,
        parameter: int,
        value: int,
        data_set: int = 0,
        *,
        ram: bool = False,
        size: int | None = None,
    ) -> None:
        par = PARAMETERS.get(parameter)
        nbytes = size or (par.type.size if par else 2)
        start = address(parameter, data_set, ram=ram)
        if nbytes == 4:
            req, resp = BONFIGLIOLI[FC_WRITE_32]
            data = start.to_bytes(2, "big") + u32(value).to_bytes(4, "big")
            self.master.execute(
                self.address, FC_WRITE_32, data, request_rule=req, response_rule=resp
            )
        else:
            self.master.write_register(self.address, start, u16(value))

    def read(self, parameter: int, data_set: int = 0) -> float:
        """A parameter of `PARAMETERS` in its unit (decimal places applied)."""
        return PARAMETERS[parameter].from_raw(self.read_raw(parameter, data_set))

    def write(self, parameter: int, value: float, data_set: int = 0, *, ram: bool = False) -> None:
        self.write_raw(parameter, PARAMETERS[parameter].to_raw(value), data_set, ram=ram)

    # state machine
    def control(self, word: int) -> None:
        """Write control word 410 (data set 0, RAM)."""
        self.write_raw(P_CONTROL_WORD, word)
        self._control = word

    def status(self) -> VectronStatus:
        return VectronStatus.decode(self.read_raw(P_STATUS_WORD))

    def state(self) -> DriveState:
        return self.status().state

    def shutdown(self) -> None:
        """0x06: starting lock-out / switched on / operation -> ready (2, 6, 8)."""
        self.control(Command.SHUTDOWN)

    def switch_on(self) -> None:
        """0x07: ready -> switched on (3)."""
        self.control(Command.SWITCH_ON)

    def enable_operation(self) -> None:
        """0x0F: switched on (or starting lock-out) -> operation enabled (4)."""
        self.control(Command.ENABLE_OPERATION)

    def disable_operation(self) -> None:
        """0x07: operation enabled -> switched on (5, per State-transition 5 392)."""
        self.control(Command.DISABLE_OPERATION)

    def disable_voltage(self) -> None:
        """0x00: -> starting lock-out (7, 9, 10, 12); the drive coasts."""
        self.control(Command.DISABLE_VOLTAGE)

    def quick_stop(self) -> None:
        """0x02: operation enabled -> quick stop (11) along the emergency ramps."""
        self.control(Command.QUICK_STOP)

    def reset_fault(self) -> None:
        """Transition 15 on a positive edge of bit 7 (15 s after the fault at the
        earliest): writes the control word without bit 7, then with it."""
        self.control(self._control & ~CW_FAULT_RESET & 0xFFFF)
        self.control(Command.FAULT_RESET)

    def start(self, hz: float | None = None) -> DriveState:
        """Set the reference (if given) and walk the state machine to operation enabled."""
        if hz is not None:
            self.set_frequency_hz(hz)
        for _ in range(4):
            st = self.state()
            if st is DriveState.OPERATION_ENABLED:
                return st
            if st in (DriveState.FAULT, DriveState.FAULT_REACTION, DriveState.NOT_READY):
                raise RuntimeError(f"the drive is in state {st.name} (0x{st.value:02X})")
            step = {
                DriveState.STARTING_LOCKOUT: Command.SHUTDOWN,
                DriveState.QUICK_STOP: Command.DISABLE_VOLTAGE,
                DriveState.READY: Command.SWITCH_ON,
                DriveState.SWITCHED_ON: Command.ENABLE_OPERATION,
            }[st]
            self.control(step)
        return self.state()

    def stop(self) -> None:
        self.disable_operation()

    def identify(self) -> dict[str, str]:
        """The manual defines no identification objects (no FC 43): the model is the
        profile's; Protocol 395 and Modbus Address 1376 are read from the drive."""
        protocol = self.read_raw(P_PROTOCOL)
        names = {0: "VCB bus", 1: "P-Bus", 2: "Modbus RTU", 3: "Modbus ASCII"}
        return {
            "vendor": "Bonfiglioli Vectron",
            "model": self.model,
            "protocol": names.get(protocol, str(protocol)),
            "address": str(self.read_raw(P_MODBUS_ADDRESS)),
        }

    # references and values
    def set_frequency_hz(self, hz: float) -> None:
        """Reference Frequency RAM 484 (the reference line value)."""
        self.write(P_REFERENCE_FREQUENCY, hz)

    def set_percentage(self, percent: float) -> None:
        """Reference Percentage RAM 524."""
        self.write(P_REFERENCE_PERCENTAGE, percent)

    def frequency_hz(self) -> float:
        """The actual frequency (ACT: Stator Frequency 210; ACU: Actual Frequency 241)."""
        return self.read(self.actual_frequency)

    def error_register(self) -> VabusError:
        """Parameter 11: why the last request failed (reading clears it)."""
        return VabusError(self.read_raw(P_ERROR_REGISTER))

    def current_error(self) -> str:
        """Current Error 260 as text ("F0000": no fault)."""
        return fault_text(self.read_raw(P_CURRENT_ERROR))

    def warnings(self) -> list[str]:
        return warnings_of(self.read_raw(P_WARNINGS))

    def set_watchdog(self, seconds: int) -> None:
        """RS232/RS485 Watchdog Timer 413 (s; 0 = off); expiry -> fault F2010."""
        self.write_raw(P_WATCHDOG, seconds)

    def select_data_set(self, data_set: int) -> None:
        """Data Set Selection 414 (0: by digital inputs)."""
        self.write_raw(P_DATA_SET_SELECTION, data_set)

    def active_data_set(self) -> int:
        return self.read_raw(P_ACTIVE_DATA_SET)

    # diagnostics
    def diagnostic_counter(self, counter: int | str) -> int:
        """FC 08 counter by sub-function (0x0B..0x12) or name (`DIAGNOSTIC_COUNTERS`)."""
        if isinstance(counter, str):
            by_name = {v: k for k, v in DIAGNOSTIC_COUNTERS.items()}
            counter = by_name[counter]
        return self.master.diagnostics(self.address, counter, 0)

    def diagnostic_counters(self) -> dict[str, int]:
        return {name: self.diagnostic_counter(sub) for sub, name in DIAGNOSTIC_COUNTERS.items()}

    def clear_counters(self) -> None:
        self.master.diagnostics(self.address, CLEAR_COUNTERS, 0)


class ACT(Vectron):
    """Vectron ACT (chapter 9)."""

    model = "ACT"
    actual_frequency = P_STATOR_FREQUENCY


class ACU(Vectron):
    """Vectron ACU (chapter 10): status bit 4 "voltage enabled" shows the mains."""

    model = "ACU"
    actual_frequency = P_ACTUAL_FREQUENCY
