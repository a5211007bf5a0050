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

from collections.abc import Iterable, Sequence

from .codecs import (
    CODECS,
    FLOAT_MAX,
    ORDERS_32,
    TYPES,
    apply_masks,
    decode,
    decoder,
    encode,
    encoder,
    field_masks,
    normalize_order,
)

ORDERS = ORDERS_32
#: the types `encode_values` and `decode_values` take: every fixed-size number type
#: of the registry (`pyrtu.pdu.codecs`)
KINDS = tuple(n for n, c in CODECS.items() if c.kind in ("int", "float"))


def _check_registers(registers: Sequence[int], want: int, what: str) -> list[int]:
    if len(registers) != want:
        raise ValueError(f"{what} takes {want} registers, got {len(registers)}")
    for reg in registers:
        if isinstance(reg, bool) or not isinstance(reg, int) or not 0 <= reg <= 0xFFFF:
            raise ValueError(f"a register is 0..65535, not {reg!r}")
    return list(registers)


def _order32(order: str) -> str:
    o = order.upper() if isinstance(order, str) else order
    if o not in ORDERS_32:
        raise ValueError(f"order must be one of {', '.join(ORDERS_32)}, not {order!r}")
    return str(o)


def _encode_integer32(kind: str, value: int, order: str) -> list[int]:
    """``value`` as two registers of ``kind`` (int32, uint32): an integer, never a float."""
    if isinstance(value, float):
        article = "an" if kind[0] in "aeiou" else "a"
        raise ValueError(f"{article} {kind} must be an integer, not {value!r}")
    return encoder(kind, _order32(order))(value)


def _decode32(kind: str, registers: Sequence[int], order: str) -> float:
    """Two registers as a number of ``kind`` (int32, uint32, float32)."""
    regs = _check_registers(registers, 2, "a 32-bit value")
    return decoder(kind, _order32(order))(regs, 0)  # type: ignore[return-value]


def encode_int32(value: int, order: str = "ABCD") -> list[int]:
    """A signed 32-bit integer as two registers."""
    return _encode_integer32("int32", value, order)


def decode_int32(registers: Sequence[int], order: str = "ABCD") -> int:
    return int(_decode32("int32", registers, order))


def encode_uint32(value: int, order: str = "ABCD") -> list[int]:
    """An unsigned 32-bit integer as two registers."""
    return _encode_integer32("uint32", value, order)


def decode_uint32(registers: Sequence[int], order: str = "ABCD") -> int:
    return int(_decode32("uint32", registers, order))


#: the largest finite float32 (FLT_MAX)
FLOAT32_MAX = FLOAT_MAX["float32"]


def encode_float32(value: float, order: str = "ABCD") -> list[int]:
    """An IEEE 754 single as two registers.

    One rule (the CLI's ``--type float32`` too): every value a float32 can hold is
    written.  A finite value is rounded to the nearest single; NaN and the
    infinities are written as themselves (devices use them as "no value").  A
    finite value that would round to infinity (beyond ``FLOAT32_MAX`` by more than
    half a unit in the last place) raises ValueError: a number never silently
    becomes infinite.
    """
    return encoder("float32", _order32(order))(value)


def decode_float32(registers: Sequence[int], order: str = "ABCD") -> float:
    return float(_decode32("float32", registers, order))


def _kind(kind: str) -> str:
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, not {kind!r}")
    return kind


def encode_values(kind: str, values: Iterable[float], order: str = "ABCD") -> list[int]:
    """Several numbers of type ``kind`` (any fixed-size number type: `KINDS`) as
    consecutive registers, in ``order`` (a 32-bit name serves 64-bit types too)."""
    encode_one = encoder(_kind(kind), normalize_order(kind, order))
    out: list[int] = []
    for v in values:
        out += encode_one(v)
    return out


def decode_values(kind: str, registers: Sequence[int], order: str = "ABCD") -> list[float]:
    """Registers (a whole number of values) as numbers of type ``kind``."""
    width = CODECS[_kind(kind)].registers
    if len(registers) % width:
        raise ValueError(
            f"{kind} values take a multiple of {width} registers (an even number for"
            f" 32-bit ones), got {len(registers)}"
        )
    regs = _check_registers(registers, len(registers), "the values")
    decode_one = decoder(kind, normalize_order(kind, order))
    return [decode_one(regs, i) for i in range(0, len(regs), width)]  # type: ignore[misc]


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
    "FLOAT_MAX",
    "KINDS",
    "ORDERS",
    "TYPES",
    "apply_masks",
    "decode",
    "decode_float32",
    "decode_int32",
    "decode_string",
    "decode_uint32",
    "decode_values",
    "encode",
    "encode_float32",
    "encode_int32",
    "encode_string",
    "encode_uint32",
    "encode_values",
    "field_masks",
]
