"""CV100 / FV100 frequency inverter (seed 003).

Registers are addressed by function-code group and index: the group gives the high
byte, the index the low byte (``"A3.02"`` -> 0x0302).  Control parameters live at
0x32xx (control word 1 at 0x3200), status parameters at 0x33xx (status word 1 at
0x3300).  Values are 16-bit; frequencies are sent x100 (50.00 Hz -> 5000), times
and currents x10 (30.0 s -> 300, 30.0 A -> 300).

Function codes: 0x03 read, 0x06 write one, 0x10 write several (values are lost at
power-off), 0x41 and 0x43 (the same writes, kept after power-off), 0x42 (manage
function codes), 0x08 (diagnosis).  RTU and ASCII.

Choices where the manual is silent (documented here and in the simulator):

* the index of ``"A6.28"`` is decimal (0x061C), as ``A3.02`` -> 0x0302 suggests;
* status word 3 has no address in the manual's table; it is read at 0x3322, the
  first address after the table;
* 0x42 has no frame layout in the manual: it is framed like FC 08 (sub-function,
  data) with the sub-functions of `Manage`.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from pyrtu.core.rules import CV100 as CV100_RULES

from .common import FlagWord, MasterLike, flag, masked_flags, masked_word, u16

#: function-code group -> high byte of the register address (section 5)
GROUPS: Mapping[str, int] = {
    **{f"A{i}": i for i in range(9)},
    **{f"B{i}": 0x0A + i for i in range(5)},
    "C0": 0x14,
    "C1": 0x15,
    "D0": 0x1E,
    "D1": 0x1F,
    "D2": 0x20,
    "U0": 0x5A,
}
CONTROL_GROUP = 0x32
STATUS_GROUP = 0x33
_GROUP_OF = {v: k for k, v in GROUPS.items()}

FC_WRITE_SAVE = 0x41
FC_MANAGE = 0x42
FC_WRITE_MULTIPLE_SAVE = 0x43

FREQUENCY_SCALE = 100
TIME_SCALE = 10
CURRENT_SCALE = 10

# control parameters (section 6.1)
CONTROL_WORD_1 = 0x3200
MAIN_SETTING = 0x3201
OPERATION_FREQUENCY_SETTING = 0x3202
DIGITAL_CLOSED_LOOP_SETTING = 0x3203
AO1_SETTING = 0x3205
DO_SETTING = 0x3207
VIRTUAL_TERMINALS = 0x3209
ACCEL_TIME_SETTING = 0x320A
DECEL_TIME_SETTING = 0x320B
CONTROL_WORD_2 = 0x3212

CONTROL_PARAMETERS: Mapping[int, str] = {
    CONTROL_WORD_1: "Control word 1",
    MAIN_SETTING: "Main setting",
    OPERATION_FREQUENCY_SETTING: "Operation frequency setting",
    DIGITAL_CLOSED_LOOP_SETTING: "Digital closed loop setting",
    AO1_SETTING: "Analog output AO1 setting",
    DO_SETTING: "Digital output DO setting",
    VIRTUAL_TERMINALS: "Virtual terminal control setting",
    ACCEL_TIME_SETTING: "Set the acceleration time",
    DECEL_TIME_SETTING: "Set the deceleration time",
    CONTROL_WORD_2: "Control command word 2",
}
#: control parameters whose value survives power-off (table "Saved after powered off")
CONTROL_SAVED = frozenset({DIGITAL_CLOSED_LOOP_SETTING, ACCEL_TIME_SETTING, DECEL_TIME_SETTING})

# status parameters (section 6.2)
STATUS_WORD_1 = 0x3300
MAIN_REFERENCE = 0x3301
SLAVE_MODEL = 0x3302
VFD_MODEL = 0x3303
SOFTWARE_VERSION = 0x3304
OPERATING_FREQUENCY = 0x3305
OUTPUT_CURRENT = 0x3306
OUTPUT_VOLTAGE = 0x3307
OUTPUT_POWER = 0x3308
ROTARY_SPEED = 0x3309
BUS_VOLTAGE = 0x330C
OUTPUT_TORQUE = 0x330E
TERMINAL_STATUS = 0x330F
FIRST_FAULT = 0x3312
SECOND_FAULT = 0x3313
LATEST_FAULT = 0x3314
FREQUENCY_SETTING = 0x3315
ACCEL_TIME_1 = 0x331C
DECEL_TIME_1 = 0x331D
COMMAND_SOURCE = 0x331E
STATUS_WORD_2 = 0x331F
MAIN_REFERENCE_SELECTOR = 0x3320
STATUS_WORD_3 = 0x3322  # not in the manual's table: see the module notes

STATUS_PARAMETERS: Mapping[int, str] = {
    STATUS_WORD_1: "VFD operation status word 1",
    MAIN_REFERENCE: "Current main reference value",
    SLAVE_MODEL: "Slave model",
    VFD_MODEL: "VFD model",
    SOFTWARE_VERSION: "Software version",
    OPERATING_FREQUENCY: "Current operating frequency",
    OUTPUT_CURRENT: "Output current",
    OUTPUT_VOLTAGE: "Output voltage",
    OUTPUT_POWER: "Output power",
    ROTARY_SPEED: "Operating rotary speed",
    0x330A: "Operating line speed",
    0x330B: "Analog close-loop feedback",
    BUS_VOLTAGE: "Bus voltage",
    0x330D: "External counter (not supported)",
    OUTPUT_TORQUE: "Output torque",
    TERMINAL_STATUS: "Digital input/output terminal status",
    0x3310: "Actual length (not supported)",
    0x3311: "Operating frequency after compensation (not supported)",
    FIRST_FAULT: "The first operating fault",
    SECOND_FAULT: "The second operating fault",
    LATEST_FAULT: "The latest operating fault",
    FREQUENCY_SETTING: "Operating frequency setting",
    0x3316: "Rotary speed setting",
    0x3317: "Analog close-loop setting",
    0x3318: "Line speed setting",
    0x3319: "AI1",
    0x331A: "AI2",
    0x331B: "Length setting (not supported)",
    ACCEL_TIME_1: "Acceleration time 1 setting",
    DECEL_TIME_1: "Deceleration time 1 setting",
    COMMAND_SOURCE: "Methods of inputting operating commands",
    STATUS_WORD_2: "VFD operating status word 2",
    MAIN_REFERENCE_SELECTOR: "Main reference frequency selector",
    0x3321: "Accumulated length (not supported)",
    STATUS_WORD_3: "VFD operating status word 3",
}

_CODE = re.compile(r"^\s*([A-DU])\s*(\d)\s*[.\-]\s*(\d{1,2})\s*$", re.IGNORECASE)


def register(code: str | int) -> int:
    """The register address of a function code: ``"A3.02"`` -> 0x0302 (the index is
    decimal: ``"A6.28"`` -> 0x061C).  An int is returned as it is (0..0xFFFF)."""
    if isinstance(code, int):
        if not 0 <= code <= 0xFFFF:
            raise ValueError(f"register address {code} is not 16-bit")
        return code
    m = _CODE.match(code)
    if not m:
        raise ValueError(f"{code!r} is not a function code like 'A3.02'")
    group = f"{m.group(1).upper()}{m.group(2)}"
    if group not in GROUPS:
        raise ValueError(f"no function-code group {group} (groups: {', '.join(GROUPS)})")
    index = int(m.group(3))
    return GROUPS[group] << 8 | index


def function_code(address: int) -> str:
    """The name of a register: ``0x0302`` -> ``"A3.02"``, ``0x3200`` -> ``"0x3200"``."""
    group = _GROUP_OF.get(address >> 8)
    if group is None:
        return f"0x{address:04X}"
    return f"{group}.{address & 0xFF:02d}"


def hz(raw: int) -> float:
    """A frequency register (1:100)."""
    return raw / FREQUENCY_SCALE


def raw_hz(value: float) -> int:
    return round(value * FREQUENCY_SCALE)


def seconds(raw: int) -> float:
    """A time register (1:10)."""
    return raw / TIME_SCALE


def raw_seconds(value: float) -> int:
    return round(value * TIME_SCALE)


def amperes(raw: int) -> float:
    """A current register (1:10)."""
    return raw / CURRENT_SCALE


# -- control word 1 and 2 --------------------------------------------------------


class Command(enum.IntEnum):
    """Control word 1 bits 2..0."""

    NONE = 0b000
    STOP_MODE_2 = 0b011  # "not support"
    EXTERNAL_FAULT_STOP = 0b100  # coast, the VFD shows an external fault
    COAST_STOP = 0b101  # stop mode 1
    STOP = 0b110  # stop mode 0: along the deceleration time
    RUN = 0b111


CW1_REVERSE = 1 << 3
CW1_JOG_FORWARD = 1 << 4
CW1_JOG_REVERSE = 1 << 5
CW1_ACC_DEC_ENABLE = 1 << 6
CW1_ENABLE = 1 << 7
CW1_MAIN_REFERENCE = 1 << 8
CW1_FAULT_RESET = 1 << 9


@dataclass(frozen=True)
class ControlWord1:
    command: Command = Command.NONE
    reverse: bool = False
    jog_forward: bool = False
    jog_reverse: bool = False
    acc_dec_enable: bool = True
    enable: bool = True
    main_reference: bool = False
    fault_reset: bool = False

    def encode(self) -> int:
        return int(self.command) | masked_word(self, _CW1_MASKS)

    @classmethod
    def decode(cls, word: int) -> ControlWord1:
        cmd = word & 0b111
        command = Command(cmd) if cmd in Command._value2member_map_ else Command.NONE
        return cls(command, **masked_flags(word, _CW1_MASKS))


#: the flag fields of `ControlWord1` and their bits
_CW1_MASKS = {
    "reverse": CW1_REVERSE,
    "jog_forward": CW1_JOG_FORWARD,
    "jog_reverse": CW1_JOG_REVERSE,
    "acc_dec_enable": CW1_ACC_DEC_ENABLE,
    "enable": CW1_ENABLE,
    "main_reference": CW1_MAIN_REFERENCE,
    "fault_reset": CW1_FAULT_RESET,
}


CW2_OPERATION_DISABLE = 1 << 0
CW2_RUN = 1 << 1
CW2_AUX_REFERENCE = 1 << 2
CW2_ENABLE = 1 << 3


@dataclass(frozen=True)
class ControlWord2:
    operation_disable: bool = False
    run: bool = False  # direction from the function codes
    aux_reference: bool = False
    enable: bool = True

    def encode(self) -> int:
        return masked_word(self, _CW2_MASKS)

    @classmethod
    def decode(cls, word: int) -> ControlWord2:
        return cls(**masked_flags(word, _CW2_MASKS))


#: the fields of `ControlWord2` and their bits
_CW2_MASKS = {
    "operation_disable": CW2_OPERATION_DISABLE,
    "run": CW2_RUN,
    "aux_reference": CW2_AUX_REFERENCE,
    "enable": CW2_ENABLE,
}


# -- status words 1-3 ------------------------------------------------------------


@dataclass(frozen=True)
class StatusWord1(FlagWord):
    running: bool = flag(0)
    reverse: bool = flag(1)
    at_reference: bool = flag(2)
    serial_control: bool = flag(3)
    serial_setting: bool = flag(4)
    alarm: bool = flag(7)
    code: int = 0  # bits 15..8: fault (alarm bit 0) or alarm (bit 7 = 1) code; 0 = normal

    @classmethod
    def decode(cls, word: int) -> StatusWord1:
        return cls(word, code=word >> 8 & 0xFF, **cls.flags_in(word))

    @property
    def fault(self) -> bool:
        return not self.alarm and self.code != 0

    def encode(self) -> int:
        return self.flag_bits() | (self.code & 0xFF) << 8


STATUS_2_BITS: Mapping[int, str] = {
    0: "jog",
    1: "closed_loop",
    2: "plc",
    3: "multi_speed",
    4: "common",
    5: "swing",
    6: "undervoltage",
    8: "servo",
    9: "customized",
    10: "synchronous_speed",
}
STATUS_3_BITS: Mapping[int, str] = {
    2: "zero_speed",
    3: "accelerating",
    4: "decelerating",
    5: "constant_speed",
    6: "pre_excitation",
    7: "tuning",
    8: "current_limiting",
    9: "dc_overvoltage_limiting",
    10: "torque_limiting",
    11: "speed_limiting",
    12: "failure",
    13: "speed_control",
    14: "torque_control",
    15: "position_control",
}


def flags(word: int, layout: Mapping[int, str]) -> frozenset[str]:
    """The names of the set bits of a status word 2 or 3."""
    return frozenset(name for bit, name in layout.items() if word >> bit & 1)


def flags_word(names: Sequence[str] | frozenset[str], layout: Mapping[int, str]) -> int:
    by_name = {n: b for b, n in layout.items()}
    return sum(1 << by_name[n] for n in names)


@dataclass(frozen=True)
class CV100Status:
    word1: StatusWord1
    word2: frozenset[str]
    word3: frozenset[str]

    def describe(self) -> str:
        w = self.word1
        parts = []
        if w.fault:
            parts.append(f"fault {w.code}")
        elif w.alarm:
            parts.append(f"alarm {w.code}")
        parts.append("running" if w.running else "stopped")
        parts.append("reverse" if w.reverse else "forward")
        if w.at_reference:
            parts.append("at reference")
        parts.extend(
            sorted(n.replace("_", " ") for n in self.word2 | self.word3 - {"speed_control"})
        )
        return ", ".join(parts)


def describe_register(address: int, value: int) -> str | None:
    """A register value in the manual's terms, for monitors (None if not special)."""
    if address == STATUS_WORD_1:
        w = StatusWord1.decode(value)
        state = "running" if w.running else "stopped"
        extra = f", fault {w.code}" if w.fault else f", alarm {w.code}" if w.alarm else ""
        return f"status word 1: {state}, {'reverse' if w.reverse else 'forward'}{extra}"
    if address == CONTROL_WORD_1:
        c = ControlWord1.decode(value)
        return f"control word 1: {c.command.name.lower()}" + (" reverse" if c.reverse else "")
    if address in (MAIN_REFERENCE, OPERATING_FREQUENCY, MAIN_SETTING, FREQUENCY_SETTING):
        return (
            f"{STATUS_PARAMETERS.get(address) or CONTROL_PARAMETERS[address]}: {hz(value):.2f} Hz"
        )
    if address == OUTPUT_CURRENT:
        return f"output current: {amperes(value):.1f} A"
    return None


class Manage(enum.IntEnum):
    """Sub-functions of 0x42 "manage function code" (the manual gives none; these
    are the simulator's and the profile's choice, framed like FC 08)."""

    UPPER_LIMIT = 0x0000  # data: register address -> highest value
    LOWER_LIMIT = 0x0001  # data: register address -> lowest value
    FACTORY_VALUE = 0x0002  # data: register address -> factory value
    DISPLAY_ADDRESS = 0x0005  # "read address of display data" -> status register shown
    SWITCH_DISPLAY = 0x0006  # "switch display data": data = status register to show


# -- profile ---------------------------------------------------------------------


class CV100:
    """A CV100/FV100 on a bus, seen from the master (RTU or ASCII: the master's mode).

    Control word 1 always carries bit 7 (host control word enable) and, for run/stop/
    jog commands, bit 6; once `set_frequency_hz` has been used, bit 8 (main
    reference from the serial setting) as well.
    """

    def __init__(self, master: MasterLike, address: int = 1) -> None:
        self.master = master
        self.address = address
        self._main_reference = False

    def _execute(self, function: int, data: bytes) -> bytes:
        req, resp = CV100_RULES[function]
        return self.master.execute(
            self.address, function, data, request_rule=req, response_rule=resp
        )

    def read(self, code: str | int) -> int:
        return self.master.read_holding_registers(self.address, register(code), 1)[0]

    def read_many(self, code: str | int, count: int) -> list[int]:
        return self.master.read_holding_registers(self.address, register(code), count)

    def write(self, code: str | int, value: int, *, save: bool = False) -> None:
        """One register: FC 06, or 0x41 with ``save=True`` (kept after power-off)."""
        addr = register(code)
        if save:
            data = addr.to_bytes(2, "big") + u16(value).to_bytes(2, "big")
            self._execute(FC_WRITE_SAVE, data)
        else:
            self.master.write_register(self.address, addr, u16(value))

    def write_many(self, code: str | int, values: Sequence[int], *, save: bool = False) -> None:
        """Consecutive registers: FC 16, or 0x43 with ``save=True``."""
        addr = register(code)
        if not save:
            self.master.write_registers(self.address, addr, [u16(v) for v in values])
            return
        body = b"".join(u16(v).to_bytes(2, "big") for v in values)
        data = addr.to_bytes(2, "big") + len(values).to_bytes(2, "big") + bytes([len(body)]) + body
        self._execute(FC_WRITE_MULTIPLE_SAVE, data)

    def manage(self, sub_function: Manage | int, data: int = 0) -> int:
        """0x42 "manage function code": returns the response's data word."""
        req = int(sub_function).to_bytes(2, "big") + u16(data).to_bytes(2, "big")
        resp = self._execute(FC_MANAGE, req)
        return int.from_bytes(resp[2:4], "big")

    # commands
    def command(self, word: ControlWord1 | int) -> None:
        """Write control word 1."""
        value = word.encode() if isinstance(word, ControlWord1) else word
        if self._main_reference:
            value |= CW1_MAIN_REFERENCE
        self.write(CONTROL_WORD_1, value)

    def run_forward(self) -> None:
        self.command(ControlWord1(Command.RUN))  # 0x00C7 in the manual's example

    def run_reverse(self) -> None:
        self.command(ControlWord1(Command.RUN, reverse=True))

    def stop(self) -> None:
        """Stop mode 0: along the deceleration time (0x00C6)."""
        self.command(ControlWord1(Command.STOP))

    def coast_stop(self) -> None:
        """Stop mode 1: coast to stop."""
        self.command(ControlWord1(Command.COAST_STOP))

    def external_fault_stop(self) -> None:
        self.command(ControlWord1(Command.EXTERNAL_FAULT_STOP))

    def jog_forward(self) -> None:
        self.command(ControlWord1(jog_forward=True))  # 0x00D0

    def jog_reverse(self) -> None:
        self.command(ControlWord1(jog_reverse=True))

    def stop_jog(self) -> None:
        self.command(ControlWord1())  # 0x00C0

    def reset_fault(self) -> None:
        self.command(ControlWord1(acc_dec_enable=False, fault_reset=True))  # 0x0280

    def control_word_2(self, word: ControlWord2) -> None:
        self.write(CONTROL_WORD_2, word.encode())

    def set_frequency_hz(self, value: float) -> None:
        """The main setting (0x3201, 1:100), selected with control word 1 bit 8."""
        self.write(MAIN_SETTING, raw_hz(value))
        if not self._main_reference:
            self._main_reference = True
            self.write(CONTROL_WORD_1, CW1_ENABLE | CW1_MAIN_REFERENCE)

    def set_accel_time(self, value: float, *, save: bool = False) -> None:
        """Acceleration time 1 (A0.06, 1:10 s)."""
        self.write("A0.06", raw_seconds(value), save=save)

    def set_decel_time(self, value: float, *, save: bool = False) -> None:
        """Deceleration time 1 (A0.07, 1:10 s)."""
        self.write("A0.07", raw_seconds(value), save=save)

    def enter_password(self, password: int) -> None:
        """Write the user password into A0.00 to get access to the function codes."""
        self.write("A0.00", password)

    # monitoring
    def status(self) -> CV100Status:
        w1 = self.read(STATUS_WORD_1)
        w2 = self.read(STATUS_WORD_2)
        w3 = self.read(STATUS_WORD_3)
        return CV100Status(
            StatusWord1.decode(w1), flags(w2, STATUS_2_BITS), flags(w3, STATUS_3_BITS)
        )

    def frequency_hz(self) -> float:
        """Current operating frequency (0x3305)."""
        return hz(self.read(OPERATING_FREQUENCY))

    def reference_hz(self) -> float:
        """Current main reference value (0x3301)."""
        return hz(self.read(MAIN_REFERENCE))

    def output_current_a(self) -> float:
        return amperes(self.read(OUTPUT_CURRENT))

    def accel_time(self) -> float:
        return seconds(self.read("A0.06"))

    def decel_time(self) -> float:
        return seconds(self.read("A0.07"))

    def faults(self) -> tuple[int, int, int]:
        """(first, second, latest) operating fault codes (0x3312-0x3314)."""
        a, b, c = self.read_many(FIRST_FAULT, 3)
        return a, b, c

    def identify(self) -> dict[str, int]:
        """Slave model, VFD model and software version (0x3302-0x3304)."""
        a, b, c = self.read_many(SLAVE_MODEL, 3)
        return {"slave_model": a, "vfd_model": b, "software_version": c}
