"""Data helpers: 32-bit values over two registers, and strings over registers.

A 32-bit value is four bytes A B C D, A the most significant.  Modbus registers
are big-endian 16-bit words, and devices disagree on how the two words (and the
bytes in them) are ordered:

=======  ===================  ==========================================
order    registers            seen as
=======  ===================  ==========================================
``ABCD`` ``[AB, CD]``         big-endian, high word first (Modicon)
``CDAB`` ``[CD, AB]``         word swap: low word first
``BADC`` ``[BA, DC]``         byte swap inside each word
``DCBA`` ``[DC, BA]``         little-endian
=======  ===================  ==========================================

::

    >>> encode_float32(1.5, "CDAB")
    [0, 16320]
    >>> decode_float32([0, 16320], "CDAB")
    1.5
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Sequence
from typing import Any

ORDERS = ("ABCD", "CDAB", "BADC", "DCBA")
KINDS = ("int32", "uint32", "float32")

# Register i of the encoded value is made of bytes (hi, lo) of "ABCD" (indices).
_LAYOUT = {
    "ABCD": ((0, 1), (2, 3)),
    "CDAB": ((2, 3), (0, 1)),
    "BADC": ((1, 0), (3, 2)),
    "DCBA": ((3, 2), (1, 0)),
}


def _order(order: str) -> tuple[tuple[int, int], tuple[int, int]]:
    try:
        return _LAYOUT[order.upper()]
    except (KeyError, AttributeError):
        raise ValueError(f"order must be one of {', '.join(ORDERS)}, not {order!r}") from None


def _to_registers(abcd: bytes, order: str) -> list[int]:
    return [abcd[hi] << 8 | abcd[lo] for hi, lo in _order(order)]


def _from_registers(registers: Sequence[int], order: str) -> bytes:
    layout = _order(order)
    if len(registers) != 2:
        raise ValueError(f"a 32-bit value takes 2 registers, got {len(registers)}")
    out = bytearray(4)
    for reg, (hi, lo) in zip(registers, layout, strict=True):
        if isinstance(reg, bool) or not isinstance(reg, int) or not 0 <= reg <= 0xFFFF:
            raise ValueError(f"a register is 0..65535, not {reg!r}")
        out[hi], out[lo] = reg >> 8, reg & 0xFF
    return bytes(out)


def _check_int(value: object, lo: int, hi: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{what} must be an integer {lo}..{hi}, not {value!r}")
    return value


def encode_int32(value: int, order: str = "ABCD") -> list[int]:
    """A signed 32-bit integer as two registers."""
    v = _check_int(value, -(2**31), 2**31 - 1, "an int32")
    return _to_registers(v.to_bytes(4, "big", signed=True), order)


def decode_int32(registers: Sequence[int], order: str = "ABCD") -> int:
    return int.from_bytes(_from_registers(registers, order), "big", signed=True)


def encode_uint32(value: int, order: str = "ABCD") -> list[int]:
    """An unsigned 32-bit integer as two registers."""
    v = _check_int(value, 0, 2**32 - 1, "a uint32")
    return _to_registers(v.to_bytes(4, "big"), order)


def decode_uint32(registers: Sequence[int], order: str = "ABCD") -> int:
    return int.from_bytes(_from_registers(registers, order), "big")


#: the largest finite float32 (FLT_MAX)
FLOAT32_MAX = 3.4028234663852886e38


def encode_float32(value: float, order: str = "ABCD") -> list[int]:
    """An IEEE 754 single as two registers.

    One rule (the CLI's ``--type float32`` too): every value a float32 can hold is
    written.  A finite value is rounded to the nearest single; NaN and the
    infinities are written as themselves (devices use them as "no value").  A
    finite value that would round to infinity (beyond ``FLOAT32_MAX`` by more than
    half a unit in the last place) raises ValueError: a number never silently
    becomes infinite.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"a float32 must be a number, not {value!r}")
    try:
        packed = struct.pack(">f", value)
    except (OverflowError, struct.error):  # struct.error: an int too big for a float
        raise ValueError(
            f"{value!r} is out of the float32 range (finite values up to"
            f" ±{FLOAT32_MAX:.8g}; nan and ±inf are written as such)"
        ) from None
    return _to_registers(packed, order)


def decode_float32(registers: Sequence[int], order: str = "ABCD") -> float:
    value: float = struct.unpack(">f", _from_registers(registers, order))[0]
    return value


_ENCODERS = {"int32": encode_int32, "uint32": encode_uint32, "float32": encode_float32}
_DECODERS = {"int32": decode_int32, "uint32": decode_uint32, "float32": decode_float32}


def encode_values(kind: str, values: Iterable[float], order: str = "ABCD") -> list[int]:
    """Several 32-bit values (``kind``: int32, uint32, float32) as consecutive registers."""
    if kind not in _ENCODERS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, not {kind!r}")
    encode: Callable[[Any, str], list[int]] = _ENCODERS[kind]
    out: list[int] = []
    for v in values:
        out += encode(v, order)
    return out


def decode_values(kind: str, registers: Sequence[int], order: str = "ABCD") -> list[float]:
    """Registers (an even number) as 32-bit values of ``kind``."""
    if kind not in _DECODERS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, not {kind!r}")
    if len(registers) % 2:
        raise ValueError(f"32-bit values take an even number of registers, got {len(registers)}")
    decode = _DECODERS[kind]
    return [decode(registers[i : i + 2], order) for i in range(0, len(registers), 2)]


def encode_string(
    text: str | bytes,
    registers: int | None = None,
    *,
    encoding: str = "ascii",
    swap: bool = False,
    pad: bytes = b"\x00",
) -> list[int]:
    """Text as registers, two characters each, the first in the high byte.

    ``registers``: the field size (padded with ``pad``; ValueError if the text is
    longer); None: just long enough.  ``swap``: first character in the low byte.
    """
    raw = text.encode(encoding) if isinstance(text, str) else bytes(text)
    if len(pad) != 1:
        raise ValueError(f"pad must be one byte, not {pad!r}")
    size = (len(raw) + 1) // 2 if registers is None else registers
    if isinstance(size, bool) or not isinstance(size, int) or size < 0:
        raise ValueError(f"registers must be a non-negative integer, not {registers!r}")
    if len(raw) > 2 * size:
        raise ValueError(f"{len(raw)} bytes do not fit {size} registers")
    raw = raw.ljust(2 * size, pad)
    if swap:
        return [raw[i + 1] << 8 | raw[i] for i in range(0, len(raw), 2)]
    return [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]


def decode_string(
    registers: Sequence[int],
    *,
    encoding: str = "ascii",
    swap: bool = False,
    strip: bytes | None = b"\x00 ",
) -> str:
    """Registers as text (see `encode_string`); trailing ``strip`` bytes removed."""
    raw = bytearray()
    for reg in registers:
        if isinstance(reg, bool) or not isinstance(reg, int) or not 0 <= reg <= 0xFFFF:
            raise ValueError(f"a register is 0..65535, not {reg!r}")
        hi, lo = reg >> 8, reg & 0xFF
        raw += bytes((lo, hi)) if swap else bytes((hi, lo))
    if strip is not None:
        raw = bytearray(raw.rstrip(strip))
    return raw.decode(encoding)


__all__ = [
    "FLOAT32_MAX",
    "KINDS",
    "ORDERS",
    "decode_float32",
    "decode_int32",
    "decode_string",
    "decode_uint32",
    "decode_values",
    "encode_float32",
    "encode_int32",
    "encode_string",
    "encode_uint32",
    "encode_values",
]
