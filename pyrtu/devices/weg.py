"""WEG CFW100, CFW320 and CFW701 frequency inverters (seeds 000, 001, 002).

Every drive parameter is a 16-bit holding register whose address is the parameter
number (P0683 -> 683).  The serial interface uses:

==========  ==============================================================
P680        status word (read only); the CFW320 adds bit 1 "run command" and
            bit 2 "fire mode"
P681        motor speed on the 13-bit scale (read only)
P682        serial control word
P683        serial speed reference on the 13-bit scale (the CFW320 manual also
            calls it P685: see `CFW320`)
P313        action on a communication error (A128 alarm / F228 fault)
P314        serial watchdog, 0.1 s (0 = off)
P316        serial interface status
P695-P697   digital outputs and analog output values (CFW320, CFW701)
==========  ==============================================================

The 13-bit scale: 8192 is the motor rated frequency P403 (the CFW701 manual says
"synchronous speed", which is the speed at the rated frequency); the signed 16-bit
range saturates at 32767/-32768, about four times P403.  A negative reference
reverses the motor; so does clearing control-word bit 2.

Profiles (`CFW100`, `CFW320`, `CFW701`) are typed helpers over a `pyrtu.Master`::

    drive = CFW701(master, address=1)
    drive.start()
    drive.set_speed_hz(30)
    drive.speed_hz(), drive.status()      # 29.98, WegStatus(running, forward, remote)
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from .common import FlagWord, MasterLike, s16, u16

# -- registers ------------------------------------------------------------------

P_SPEED_REFERENCE_MONITOR = 1
P_MOTOR_SPEED = 2
P_MOTOR_CURRENT = 3
P_INVERTER_STATE = 6
P_PRESENT_ALARM = 48
P_PRESENT_FAULT = 49
P_ACCEL_TIME = 100
P_DECEL_TIME = 101
P_ACCEL_TIME_2 = 102
P_DECEL_TIME_2 = 103
P_JOG_REFERENCE = 122
P_MAX_FREQUENCY = 134
P_SERIAL_ADDRESS = 308
P_BAUD_RATE = 310
P_BYTE_FORMAT = 311
P_PROTOCOL = 312
P_ERROR_ACTION = 313
P_WATCHDOG = 314
P_INTERFACE_STATUS = 316
P_RATED_CURRENT = 401
P_RATED_SPEED = 402
P_RATED_FREQUENCY = 403
P_STATUS = 680
P_SPEED = 681
P_CONTROL = 682
P_REFERENCE = 683
P_REFERENCE_ALT = 685
P_DIGITAL_OUTPUTS = 695
P_ANALOG_OUTPUT_1 = 696
P_ANALOG_OUTPUT_2 = 697

#: alarm and fault numbers of the serial watchdog
A128 = 128
F228 = 228

SCALE_13BIT = 8192
ANALOG_FULL_SCALE = 0x7FFF

#: the telegram limit of section 6: "cannot exceed 64 bytes"
MAX_TELEGRAM = 64


def hz_to_13bit(hz: float, rated_hz: float) -> int:
    """A frequency on the 13-bit scale (8192 = ``rated_hz``), saturating at the
    signed 16-bit limits (about 4 x rated)."""
    if rated_hz <= 0:
        raise ValueError("the rated frequency (P403) must be positive")
    value = round(hz * SCALE_13BIT / rated_hz)
    return max(-0x8000, min(0x7FFF, value))


def hz_from_13bit(value: int, rated_hz: float) -> float:
    """The frequency of a 13-bit-scale register value (raw 0..65535 or signed)."""
    return s16(value) * rated_hz / SCALE_13BIT


def rpm_to_13bit(rpm: float, synchronous_rpm: float) -> int:
    """The CFW701 wording: 8192 = synchronous speed (rpm)."""
    return hz_to_13bit(rpm, synchronous_rpm)


def rpm_from_13bit(value: int, synchronous_rpm: float) -> float:
    return hz_from_13bit(value, synchronous_rpm)


# -- status word P680 -----------------------------------------------------------

STATUS_BITS: Mapping[int, str] = {
    5: "second_ramp",
    6: "config_mode",
    7: "alarm",
    8: "running",
    9: "enabled",
    10: "forward",
    11: "jog",
    12: "remote",
    13: "undervoltage",
    15: "fault",
}
#: CFW320 (seed 001, table 4.1): bits 1 and 2 are used; the rest as the others
STATUS_BITS_CFW320: Mapping[int, str] = {1: "run_command", 2: "fire_mode", **STATUS_BITS}


@dataclass(frozen=True)
class WegStatus(FlagWord):
    """P680 decoded.  ``run_command``/``fire_mode`` are None on models without them."""

    second_ramp: bool = False
    config_mode: bool = False
    alarm: bool = False
    running: bool = False
    enabled: bool = False
    forward: bool = False
    jog: bool = False
    remote: bool = False
    undervoltage: bool = False
    fault: bool = False
    run_command: bool | None = None
    fire_mode: bool | None = None

    def describe(self) -> str:
        """For people: ``"running, forward, remote"``, ``"fault, stopped, ..."``."""
        parts = ["fault"] if self.fault else []
        if self.alarm:
            parts.append("alarm")
        parts.append("running" if self.running else "stopped")
        parts.append("forward" if self.forward else "reverse")
        parts.append("remote" if self.remote else "local")
        if not self.enabled:
            parts.append("disabled")
        for name in ("jog", "second_ramp", "undervoltage", "config_mode", "fire_mode"):
            if getattr(self, name) is True:
                parts.append(name.replace("_", " "))
        return ", ".join(parts)


def decode_status(word: int, model: str = "CFW701") -> WegStatus:
    """P680 of ``model`` ("CFW100", "CFW320", "CFW701") as named flags."""
    layout = STATUS_BITS_CFW320 if model.upper() == "CFW320" else STATUS_BITS
    flags = {name: bool(word >> bit & 1) for bit, name in layout.items()}
    return WegStatus(word & 0xFFFF, **flags)


def encode_status(status: WegStatus, model: str = "CFW701") -> int:
    layout = STATUS_BITS_CFW320 if model.upper() == "CFW320" else STATUS_BITS
    word = 0
    for bit, name in layout.items():
        if getattr(status, name) is True:
            word |= 1 << bit
    return word


# -- control word P682 ----------------------------------------------------------

CONTROL_BITS: Mapping[int, str] = {
    0: "run",
    1: "enable",
    2: "forward",
    3: "jog",
    4: "remote",
    5: "second_ramp",
    7: "fault_reset",
}
#: CFW701 (seed 002, table 3.4) adds fast stop and the PID manual/automatic bits
CONTROL_BITS_CFW701: Mapping[int, str] = {
    **CONTROL_BITS,
    6: "fast_stop",
    13: "pid_main_manual",
    14: "pid_external1_manual",
    15: "pid_external2_manual",
}


@dataclass(frozen=True)
class WegControl:
    """P682 as named flags.  ``forward`` is bit 2: run in the direction of the
    reference sign (1) or against it (0)."""

    run: bool = False
    enable: bool = False
    forward: bool = True
    jog: bool = False
    remote: bool = False
    second_ramp: bool = False
    fault_reset: bool = False
    fast_stop: bool = False
    pid_main_manual: bool = False
    pid_external1_manual: bool = False
    pid_external2_manual: bool = False

    def encode(self, model: str = "CFW701") -> int:
        """The P682 word; bits the model does not have raise ValueError."""
        layout = CONTROL_BITS_CFW701 if model.upper() == "CFW701" else CONTROL_BITS
        names = set(layout.values())
        word = 0
        for bit, name in CONTROL_BITS_CFW701.items():
            if getattr(self, name):
                if name not in names:
                    raise ValueError(f"{model} has no control-word bit {name!r}")
                word |= 1 << bit
        return word

    @classmethod
    def decode(cls, word: int, model: str = "CFW701") -> WegControl:
        layout = CONTROL_BITS_CFW701 if model.upper() == "CFW701" else CONTROL_BITS
        return cls(**{name: bool(word >> bit & 1) for bit, name in layout.items()})


def control_word(
    *,
    run: bool = False,
    enable: bool = True,
    forward: bool = True,
    jog: bool = False,
    remote: bool = True,
    second_ramp: bool = False,
    fault_reset: bool = False,
) -> int:
    """The P682 value for the common commands (defaults: enabled, forward, remote)."""
    return WegControl(run, enable, forward, jog, remote, second_ramp, fault_reset).encode("CFW100")


def reference_direction(control: int, reference: int) -> bool:
    """True (forward) or False (reverse) from P682 bit 2 and the sign of P683:
    bit 2 = 1 keeps the reference's sign, bit 2 = 0 inverts it."""
    keep = bool(control & 0x4)
    positive = s16(reference) >= 0
    return positive if keep else not positive


# -- serial supervision ---------------------------------------------------------


class ErrorAction(enum.IntEnum):
    """P313: what the drive does on a communication error (A128/F228)."""

    INACTIVE = 0
    RAMP_STOP = 1  # "disable via Run/Stop"
    GENERAL_DISABLE = 2
    GO_TO_LOCAL = 3
    LOCAL_KEEP_COMMANDS = 4
    CAUSE_FAULT = 5


class InterfaceStatus(enum.IntEnum):
    """P316."""

    INACTIVE = 0
    ACTIVE = 1
    WATCHDOG_ERROR = 2


def apply_error_action(control: int, action: ErrorAction | int) -> int:
    """P682 after the drive "automatically writes" the P313 action into it."""
    action = ErrorAction(action)
    if action is ErrorAction.RAMP_STOP:
        return control & ~0x01
    if action is ErrorAction.GENERAL_DISABLE:
        return control & ~0x02
    if action in (ErrorAction.GO_TO_LOCAL, ErrorAction.LOCAL_KEEP_COMMANDS):
        return control & ~0x10
    return control


# -- models and parameters ------------------------------------------------------


@dataclass(frozen=True)
class WegParam:
    """One parameter: number, name, factory value, range (raw register values),
    ``decimals`` of the transmitted integer, read only (RO), changeable only with
    the motor stopped (CFG), signed."""

    number: int
    name: str
    default: int
    low: int = 0
    high: int = 0xFFFF
    decimals: int = 0
    unit: str = ""
    ro: bool = False
    cfg: bool = False
    signed: bool = False

    def accepts(self, raw: int) -> bool:
        value = s16(raw) if self.signed else raw & 0xFFFF
        return self.low <= value <= self.high


@dataclass(frozen=True)
class WegModel:
    name: str
    functions: frozenset[int]
    baud_rates: tuple[int, ...]
    reference_registers: tuple[int, ...]
    digital_outputs: int  # how many DOs P695 drives (0: no P695)
    firmware: str = "V1.00"
    vendor: str = "WEG"
    status_bits: Mapping[int, str] = field(default_factory=lambda: STATUS_BITS)
    control_bits: Mapping[int, str] = field(default_factory=lambda: CONTROL_BITS)

    @property
    def has_analog_outputs(self) -> bool:
        return self.digital_outputs > 0


CFW100_MODEL = WegModel(
    "CFW100",
    frozenset({3, 4, 6, 16, 43}),
    (9600, 19200, 38400),
    (P_REFERENCE,),
    0,
)
CFW320_MODEL = WegModel(
    "CFW320",
    frozenset({1, 2, 3, 5, 6, 15, 16, 22, 23, 43}),
    (9600, 19200, 38400, 57600, 76800),
    (P_REFERENCE, P_REFERENCE_ALT),
    4,
    status_bits=STATUS_BITS_CFW320,
)
CFW701_MODEL = WegModel(
    "CFW701",
    frozenset({1, 2, 3, 4, 5, 6, 15, 16, 43}),
    (9600, 19200, 38400, 57600),
    (P_REFERENCE,),
    5,
    control_bits=CONTROL_BITS_CFW701,
)
MODELS: Mapping[str, WegModel] = {m.name: m for m in (CFW100_MODEL, CFW320_MODEL, CFW701_MODEL)}


def parameters(model: WegModel | str) -> dict[int, WegParam]:
    """The parameters a simulated ``model`` has (number -> `WegParam`).

    The serial parameters come from the seed manuals; the monitoring and ramp
    parameters (P001-P007, P048/P049, P100-P103, P122, P134, P401-P403) are the
    ones the manuals name, with the ranges and factory values of the drives'
    programming manuals, simplified: frequencies in 0.1 Hz on all three models.
    Every parameter a model's manual names is here (a test checks it against the
    manuals' text), also those the manuals only refer to: the CFW320's P028 (the
    accessory detected), the CFW701's P202 (type of control), the output functions
    P251/P254 (analog) and P275-P279 (digital, CFW701).  Those are stored, not
    interpreted; their ranges are the simulator's choice (the manuals give none).
    """
    m = MODELS[model.upper()] if isinstance(model, str) else model
    p = WegParam
    table = [
        p(0, "Access to parameters", 0, 0, 9999),
        p(1, "Speed reference", 0, decimals=1, unit="Hz", ro=True),
        p(2, "Motor speed", 0, unit="Hz", ro=True),
        p(3, "Motor current", 0, decimals=1, unit="A", ro=True),
        p(4, "DC link voltage", 311, unit="V", ro=True),
        p(5, "Output frequency", 0, decimals=1, unit="Hz", ro=True),
        p(6, "Inverter state", 0, 0, 9, ro=True),
        p(7, "Output voltage", 0, unit="V", ro=True),
        p(48, "Present alarm", 0, ro=True),
        p(49, "Present fault", 0, ro=True),
        p(100, "Acceleration time", 50, 1, 9999, 1, "s"),
        p(101, "Deceleration time", 100, 1, 9999, 1, "s"),
        p(102, "Acceleration time 2nd ramp", 50, 1, 9999, 1, "s"),
        p(103, "Deceleration time 2nd ramp", 100, 1, 9999, 1, "s"),
        p(105, "1st/2nd ramp selection", 0, 0, 9, cfg=True),
        p(122, "JOG reference", 50, 0, 4000, 1, "Hz"),
        p(134, "Maximum frequency", 660, 0, 4000, 1, "Hz"),
        *(p(n, name, 0, 0, 20, cfg=True) for n, name in _SOURCES.items()),
        p(
            308,
            "Serial address",
            1,
            0 if m.name == "CFW701" else 1,
            255 if m.name == "CFW701" else 247,
            cfg=True,
        ),
        p(310, "Serial baud rate", 1, 0, len(m.baud_rates) - 1, cfg=True),
        p(311, "Serial byte configuration", 0 if m.name == "CFW701" else 1, 0, 5, cfg=True),
        p(313, "Communication error action", 1, 0, 5, cfg=True),
        p(314, "Serial watchdog", 0, 0, 9990, 1, "s", cfg=True),
        p(316, "Serial interface status", 1, 0, 2, ro=True),
        p(401, "Motor rated current", 30, 0, 2000, 1, "A", cfg=True),
        p(402, "Motor rated speed", 1720, 0, 24000, unit="rpm", cfg=True),
        p(403, "Motor rated frequency", 60, 1, 400, unit="Hz", cfg=True),
        p(P_STATUS, "Status word", 0, ro=True),
        p(P_SPEED, "Motor speed in 13 bits", 0, -32768, 32767, ro=True, signed=True),
        p(P_CONTROL, "Serial control word", 0),
        p(P_REFERENCE, "Serial speed reference", 0, -32768, 32767, signed=True),
    ]
    if m.name == "CFW701":
        table.append(p(107, "Fast stop time", 50, 1, 9999, 1, "s"))
    if m.name in ("CFW320", "CFW701"):
        table.append(p(312, "Serial protocol", 2, 0, 5, cfg=True))
        dos = (1 << m.digital_outputs) - 1
        table.append(p(P_DIGITAL_OUTPUTS, "Digital outputs", 0, 0, dos))
        signed_ao = m.name == "CFW701"
        low, high = (-32768, 32767) if signed_ao else (0, 0xFFFF)
        table.append(p(P_ANALOG_OUTPUT_1, "Analog output value 1", 0, low, high, signed=signed_ao))
        table.append(p(P_ANALOG_OUTPUT_2, "Analog output value 2", 0, low, high, signed=signed_ao))
    if m.name == "CFW320":
        table.append(p(P_REFERENCE_ALT, "Speed reference (P683)", 0, -32768, 32767, signed=True))
        # CFW320 manual 6.1 step 2: P028 shows the communication accessory detected
        table.append(p(28, "Communication accessory configuration", 0, ro=True))
    if m.name == "CFW701":
        # CFW701 manual, P0682 bit 6: fast stop needs a vector control type (P0202)
        table.append(p(202, "Type of control", 0, 0, 5, cfg=True))
        # CFW701 manual, P0695: the digital outputs' functions are P0275 to P0279
        table += [p(275 + i, f"DO{i + 1} function", 0, 0, 255) for i in range(5)]
    if m.name in ("CFW320", "CFW701"):
        # both manuals, P696/P697: the analog outputs' functions are P251 and P254
        table += [p(n, f"Analog output function (P{n})", 0, 0, 255) for n in (251, 254)]
    return {x.number: x for x in sorted(table, key=lambda x: x.number)}


_SOURCES = {
    220: "LOC/REM selection source",
    221: "Speed reference selection - local",
    222: "Speed reference selection - remote",
    223: "FWD/REV selection - local",
    224: "Run/stop selection - local",
    225: "JOG selection - local",
    226: "FWD/REV selection - remote",
    227: "Run/stop selection - remote",
    228: "JOG selection - remote",
}


def describe_register(model: str, address: int, value: int) -> str | None:
    """A register value in the drive's terms, for monitors (None if not special)."""
    if address == P_STATUS:
        return f"P680 status: {decode_status(value, model).describe()}"
    if address == P_CONTROL:
        ctl = WegControl.decode(value, model)
        names = [n for n in CONTROL_BITS_CFW701.values() if getattr(ctl, n)]
        return f"P682 control: {', '.join(names) or 'none'}"
    if address in (P_SPEED, P_REFERENCE) or (
        model.upper() == "CFW320" and address == P_REFERENCE_ALT
    ):
        what = "speed" if address == P_SPEED else "reference"
        return f"P{address} {what}: {s16(value)}/8192 of P403"
    if address == P_INTERFACE_STATUS and value in (0, 1, 2):
        return f"P316 serial interface: {InterfaceStatus(value).name.lower()}"
    return None


def describe_cfw100(address: int, value: int) -> str | None:
    """`describe_register` of a CFW100 (the hook of templates/cfw100.toml)."""
    return describe_register("CFW100", address, value)


def describe_cfw320(address: int, value: int) -> str | None:
    """`describe_register` of a CFW320 (the hook of templates/cfw320.toml)."""
    return describe_register("CFW320", address, value)


def describe_cfw701(address: int, value: int) -> str | None:
    """`describe_register` of a CFW701 (the hook of templates/cfw701.toml)."""
    return describe_register("CFW701", address, value)


# -- profiles -------------------------------------------------------------------


class WegDrive:
    """A WEG drive on a bus, seen from the master.  Use `CFW100`, `CFW320`, `CFW701`.

    ``rated_hz``: the motor rated frequency P403 for the 13-bit scale (None: read
    from the drive at first use).  The profile keeps the control word it last wrote
    and changes one command at a time (`start`, `stop`, `set_direction`, ...).
    """

    model: WegModel = CFW701_MODEL

    def __init__(
        self,
        master: MasterLike,
        address: int = 1,
        *,
        rated_hz: float | None = None,
        reference_register: int = P_REFERENCE,
    ) -> None:
        if reference_register not in self.model.reference_registers:
            raise ValueError(f"{self.model.name} has no speed reference at P{reference_register}")
        self.master = master
        self.address = address
        self._rated_hz = rated_hz
        self.reference_register = reference_register
        self._control = WegControl(enable=True, forward=True, remote=True)

    # parameters
    def read(self, parameter: int) -> int:
        """One parameter's raw register value (0..65535)."""
        return self.master.read_holding_registers(self.address, parameter, 1)[0]

    def read_many(self, first: int, count: int) -> list[int]:
        return self.master.read_holding_registers(self.address, first, count)

    def write(self, parameter: int, value: int) -> None:
        """Write one parameter (signed values are sent as two's complement)."""
        self.master.write_register(self.address, parameter, u16(value))

    def write_many(self, first: int, values: Sequence[int]) -> None:
        self.master.write_registers(self.address, first, [u16(v) for v in values])

    def identify(self) -> dict[str, str]:
        """FC 43 basic objects: vendor, product code, revision ('Vx.xx')."""
        objects = self.master.read_device_identification(self.address, 1, 0)
        names = {0: "vendor", 1: "product_code", 2: "revision"}
        return {
            names.get(k, f"object_{k}"): v.decode("ascii", "replace") for k, v in objects.items()
        }

    # state
    def status(self) -> WegStatus:
        """P680 decoded."""
        return decode_status(self.read(P_STATUS), self.model.name)

    def control(self) -> WegControl:
        """P682 as the drive holds it."""
        return WegControl.decode(self.read(P_CONTROL), self.model.name)

    def rated_hz(self) -> float:
        """P403 (cached after the first read)."""
        if self._rated_hz is None:
            self._rated_hz = float(self.read(P_RATED_FREQUENCY))
        return self._rated_hz

    def speed_hz(self) -> float:
        """Motor speed (P681) in Hz; negative = reverse."""
        return hz_from_13bit(self.read(P_SPEED), self.rated_hz())

    def frequency_hz(self) -> float:
        """The same as `speed_hz` (the name the other profiles use)."""
        return self.speed_hz()

    def reference_hz(self) -> float:
        return hz_from_13bit(self.read(self.reference_register), self.rated_hz())

    def set_speed_hz(self, hz: float) -> None:
        """Speed reference on the 13-bit scale; negative reverses (with bit 2 = 1)."""
        self.write(self.reference_register, hz_to_13bit(hz, self.rated_hz()))

    def motor_current_a(self) -> float:
        return self.read(P_MOTOR_CURRENT) / 10

    # commands
    def set_control(self, control: WegControl) -> None:
        """Write P682 as given and remember it."""
        self.write(P_CONTROL, control.encode(self.model.name))
        self._control = replace(control, fault_reset=False)

    def _change(self, **bits: bool) -> None:
        self.set_control(replace(self._control, **bits))

    def start(self, forward: bool = True) -> None:
        """Run (bit 0) with general enable, in remote, along the acceleration ramp."""
        self._change(run=True, enable=True, remote=True, forward=forward, jog=False)

    def stop(self) -> None:
        """Stop along the deceleration ramp (bit 0 = 0)."""
        self._change(run=False, jog=False)

    def disable(self) -> None:
        """Remove the general enable: the motor coasts."""
        self._change(run=False, enable=False)

    def enable(self) -> None:
        self._change(enable=True)

    def set_direction(self, forward: bool) -> None:
        """Bit 2: run in the reference's direction (True) or against it."""
        self._change(forward=forward)

    def jog(self, on: bool = True) -> None:
        self._change(jog=on, enable=True, remote=True)

    def set_remote(self, remote: bool = True) -> None:
        self._change(remote=remote)

    def second_ramp(self, on: bool = True) -> None:
        self._change(second_ramp=on)

    def reset_fault(self) -> None:
        """Bit 7 "fault reset", then the control word without it."""
        self.write(P_CONTROL, replace(self._control, fault_reset=True).encode(self.model.name))
        self.set_control(self._control)

    # supervision
    def set_watchdog(self, seconds: float, action: ErrorAction | int | None = None) -> None:
        """P314 (0.1 s; 0 = off) and, if given, the P313 action."""
        if action is not None:
            self.write(P_ERROR_ACTION, int(ErrorAction(action)))
        self.write(P_WATCHDOG, round(seconds * 10))

    def interface_status(self) -> InterfaceStatus:
        return InterfaceStatus(self.read(P_INTERFACE_STATUS))

    def alarm(self) -> int:
        """P048, the present alarm (128: serial timeout A128)."""
        return self.read(P_PRESENT_ALARM)

    def fault(self) -> int:
        """P049, the present fault (228: serial timeout F228)."""
        return self.read(P_PRESENT_FAULT)

    # outputs
    def set_digital_outputs(self, bits: int) -> None:
        """P695: bit n closes DO(n+1) (if programmed for "P695 value")."""
        if not self.model.digital_outputs:
            raise ValueError(f"the {self.model.name} has no digital output word P695")
        if not 0 <= bits < 1 << self.model.digital_outputs:
            raise ValueError(f"{self.model.name} has {self.model.digital_outputs} digital outputs")
        self.write(P_DIGITAL_OUTPUTS, bits)

    def set_analog_output(self, output: int, fraction: float) -> None:
        """P696 (output 1) or P697 (output 2) on the 15-bit scale: 1.0 = 7FFFh = 100 %."""
        if not self.model.has_analog_outputs:
            raise ValueError(f"the {self.model.name} has no analog output words P696/P697")
        if output not in (1, 2):
            raise ValueError("analog output value 1 (P696) or 2 (P697)")
        value = max(-0x8000, min(0x7FFF, round(fraction * ANALOG_FULL_SCALE)))
        self.write(P_ANALOG_OUTPUT_1 + output - 1, value)


class CFW100(WegDrive):
    """WEG CFW100 (FC 03/04/06/16/43)."""

    model = CFW100_MODEL


class CFW320(WegDrive):
    """WEG CFW320.  The manual defines the serial speed reference as P683 ("Serial/USB
    Speed Ref.") but its direction table and memory map call it P685.  The profile
    writes P683 by default (``reference_register=685`` writes P685); the simulator
    takes either, as one and the same reference."""

    model = CFW320_MODEL

    def fire_mode(self) -> bool:
        return bool(self.status().fire_mode)


class CFW701(WegDrive):
    """WEG CFW701 (13-bit scale on the synchronous speed = rated frequency P403)."""

    model = CFW701_MODEL

    def fast_stop(self) -> None:
        """Bit 6 (not with V/f or VVW control)."""
        self._change(fast_stop=True)

    def speed_rpm(self, synchronous_rpm: float) -> float:
        """P681 in rpm, as the CFW701 manual states it (8192 = synchronous speed)."""
        return rpm_from_13bit(self.read(P_SPEED), synchronous_rpm)
