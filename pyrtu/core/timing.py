"""Character timing: character time, t1.5 and t3.5 from baud rate and byte format.

Modbus over Serial Line V1.02, 2.5.1.1: silences of 1.5 and 3.5 character times;
above 19200 baud the fixed values 750 us and 1750 us.  The WEG manuals (CFW100
4.2.5, table 4.1) keep the 19200-baud values above 19200: T11bits = 573 us and
T3.5 = 2.005 ms (t1.5 = 1.5 x 573 us = 860 us).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pyrtu.core._errtypes import ArgumentTypeError

TIMING_RULES = ("modbus", "weg")
MODES = ("rtu", "ascii")
PARITIES = ("N", "E", "O", "M", "S")

#: The baud rates every layer accepts (`LineConfig`, the framers, the masters and
#: slaves, the virtual bus, the TOML loader and the command line check them here).
#: 50 is the slowest rate termios names (B50); 4000000 the fastest one Linux names
#: (B4000000) and the top of pyserial's ``Serial.BAUDRATES``.  Faster adapters exist,
#: but the framers keep time in whole microseconds: at 4 Mbaud a 9-bit character
#: (7N1) lasts 2.25 us, already rounded by 11 %; much above, t1.5 and the answer
#: length timing lose their meaning.
MIN_BAUDRATE = 50
MAX_BAUDRATE = 4_000_000
STOPBITS = (1, 1.5, 2)
BYTESIZES = (7, 8)


def check_baudrate(value: object) -> int:
    """``value`` as a baud rate; the one check of every layer (TypeError for a
    non-integer, ValueError out of range; both messages name ``baudrate``)."""
    text = f"baudrate must be an integer {MIN_BAUDRATE}..{MAX_BAUDRATE}, not {value!r}"
    if isinstance(value, bool) or not isinstance(value, int):
        raise ArgumentTypeError(text)
    if not MIN_BAUDRATE <= value <= MAX_BAUDRATE:
        raise ValueError(text)
    return value


def check_timing(value: object) -> str:
    """``value`` as a timing rule above 19200 baud: "modbus" or "weg"."""
    if not isinstance(value, str) or value not in TIMING_RULES:
        raise ValueError(f"timing must be 'modbus' or 'weg', not {value!r}")
    return value


def check_mode(value: object) -> str:
    """``value`` as a transmission mode: "rtu" or "ascii" (Serial Line V1.02, 2.5)."""
    if not isinstance(value, str) or value not in MODES:
        raise ValueError(f"mode must be 'rtu' or 'ascii', not {value!r}")
    return value


_PARITY_NAMES = {"NONE": "N", "EVEN": "E", "ODD": "O", "MARK": "M", "SPACE": "S"}


def check_parity(value: object) -> str:
    """``value`` as a parity letter: N, E, O, M, S or the names none, even, odd,
    mark, space (any case)."""
    text = f"parity must be one of {', '.join(PARITIES)}, not {value!r}"
    if not isinstance(value, str):
        raise ArgumentTypeError(text)
    word = value.strip().upper()
    letter = _PARITY_NAMES.get(word, word)
    if letter not in PARITIES:
        raise ValueError(text)
    return letter


def check_bytesize(value: object) -> int:
    """``value`` as data bits per character (7 or 8: Serial Line V1.02, 2.5)."""
    text = f"bytesize must be 7 or 8, not {value!r}"
    if isinstance(value, bool) or not isinstance(value, int):
        raise ArgumentTypeError(text)
    if value not in BYTESIZES:
        raise ValueError(text)
    return value


def check_stopbits(value: object) -> float:
    """``value`` as stop bits (1, 1.5 or 2)."""
    text = f"stopbits must be 1, 1.5 or 2, not {value!r}"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ArgumentTypeError(text)
    if value not in STOPBITS:
        raise ValueError(text)
    return value


@dataclass(frozen=True, slots=True)
class Timing:
    """Integer microseconds, as the C core uses them."""

    char_us: int
    t15_us: int
    t35_us: int

    @property
    def char(self) -> float:
        return self.char_us / 1e6

    @property
    def t15(self) -> float:
        return self.t15_us / 1e6

    @property
    def t35(self) -> float:
        return self.t35_us / 1e6


def bits_per_char(parity: str = "E", stopbits: float = 1, bytesize: int = 8) -> int:
    """Start bit + data bits + parity bit + stop bits (11 for 8E1, 8O1, 8N2; 10 for 8N1)."""
    parity = check_parity(parity)
    bytesize = check_bytesize(bytesize)
    stopbits = check_stopbits(stopbits)
    return 1 + bytesize + (0 if parity == "N" else 1) + int(stopbits + 0.5)


def _div_round(num: int, den: int) -> int:
    return (2 * num + den) // (2 * den)


def compute_timing(baudrate: int, bits: int, rule: str = "modbus") -> Timing:
    """The pure-Python twin of rtu_timing_init (same integer arithmetic)."""
    check_baudrate(baudrate)
    check_timing(rule)
    if not 7 <= bits <= 12:
        raise ValueError(f"bits per character must be 7..12, not {bits}")
    bits_us = bits * 1_000_000
    char_us = _div_round(bits_us, baudrate)
    if baudrate <= 19200:
        return Timing(
            char_us, _div_round(bits_us * 3, baudrate * 2), _div_round(bits_us * 7, baudrate * 2)
        )
    if rule == "modbus":
        return Timing(char_us, 750, 1750)
    return Timing(char_us, 860, 2005)


def seconds_to_us(value: float, name: str) -> int:
    """A duration in seconds as integer microseconds, checked."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ArgumentTypeError(f"{name} must be a non-negative number of seconds, not {value!r}")
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a non-negative number of seconds, not {value!r}")
    return round(value * 1_000_000)


def check_seconds(name: str, value: object, positive: bool = False) -> float:
    """``value`` as float seconds: a finite number, above 0 with ``positive``, else
    at least 0 (NaN and infinity refused).  Otherwise "``name`` must be a positive
    (non-negative) number of seconds, not ...": an `ArgumentTypeError` (a TypeError
    that is a ValueError too) for what is not a number (bool included), a ValueError
    for a number out of range; ``name`` is the argument in the caller's terms (a
    keyword, a TOML key with its colon).  The one duration check of every layer:
    masters, slaves, the gateway, the bridge, `pyrtu.drivers.reconnect.Backoff`."""
    error: type[Exception] = ArgumentTypeError
    if not isinstance(value, bool) and isinstance(value, int | float):
        if 0 < value < math.inf if positive else 0 <= value < math.inf:  # (NaN fails)
            return float(value)
        error = ValueError
    what = "a positive" if positive else "a non-negative"
    raise error(f"{name} must be {what} number of seconds, not {value!r}")


def positive_seconds(value: object, name: str) -> float:
    """``value`` as float seconds: ValueError naming ``name`` unless it is a finite
    number above 0 (an inter-character limit, a timeout): `check_seconds`."""
    return check_seconds(name, value, True)


def apply_overrides(base: Timing, t15: float | None, t35: float | None) -> Timing:
    t15_us = base.t15_us if t15 is None else seconds_to_us(t15, "t15")
    t35_us = base.t35_us if t35 is None else seconds_to_us(t35, "t35")
    return Timing(base.char_us, t15_us, t35_us)
