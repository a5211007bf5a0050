"""The register types: one table, `CODECS` (a type's name -> its `Codec`), that every
consumer uses: the poller's points (``[[point]] type = ...``, so device templates
too), ``pyrtu read/write --type``, `pyrtu.data` and the bridge's set commands.  A
new type is one row of the table.

==============  =========  ======================================================
type            registers  value
==============  =========  ======================================================
``bool``        (a bit)    a coil or discrete input; in a register: its ``bit``
``int8``        1          a signed byte of the register: ``order`` high or low
``uint8``       1          an unsigned byte (high or low)
``int16``       1          two's complement
``uint16``      1
``int32``       2          two's complement
``uint32``      2
``int64``       4          two's complement
``uint64``      4
``float16``     1          IEEE 754 half (binary16)
``float32``     2          IEEE 754 single
``float64``     4          IEEE 754 double
``bcd16``       1          four decimal digits, 0..9999
``bcd32``       2          eight decimal digits, 0..99999999
``string``      count      two characters per register (Latin-1)
``string1``     count      one character per register (its low byte)
==============  =========  ======================================================

Orders name the bytes of a value, ``A`` the most significant, in the order the
registers carry them (Modbus registers are big-endian 16-bit words):

* 32-bit values: ``ABCD`` (big-endian, Modicon), ``CDAB`` (word swap, low word
  first), ``BADC`` (byte swap in each word), ``DCBA`` (little-endian);
* 64-bit values: ``ABCDEFGH``, ``GHEFCDAB`` (words reversed), ``BADCFEHG`` (bytes
  swapped in each word), ``HGFEDCBA`` (little-endian): the same four rules, so a
  32-bit name given to a 64-bit type means its 64-bit equivalent (``CDAB`` ->
  ``GHEFCDAB``) and the reverse (one device-wide order serves both widths);
* one register (16-bit types, ``bcd16``, strings' registers): ``AB`` or ``BA``
  (the two bytes swapped); a 32- or 64-bit name gives its byte rule (``ABCD`` and
  ``CDAB``: ``AB``; ``BADC`` and ``DCBA``: ``BA``);
* 8-bit types: ``high`` (the register's first byte, the default) or ``low``; a
  multi-byte name leaves the default.

Strings are trimmed on reading (cut at the first NUL, trailing spaces removed) and
padded with NULs on writing; a text longer than the registers is refused.  BCD
digits above 9 are no number: decoding gives None (the value is bad).  Floats take
NaN and the infinities both ways (devices use them as "no value"); a finite value
beyond a float's range is refused, never made infinite.

`decoder` and `encoder` build a type's functions once per (type, order, count)
(the poller's points keep them): ``decode(block, i)`` reads the value at index
``i`` of a block of registers, ``encode(value)`` gives its registers.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

#: a decoded value (None: no value, such as a BCD register holding a digit above 9)
Value = bool | int | float | str
Decode = Callable[[Sequence[int], int], Value | None]
Encode = Callable[[Any], list[int]]

ORDERS_8 = ("high", "low")
ORDERS_16 = ("AB", "BA")
ORDERS_32 = ("ABCD", "CDAB", "BADC", "DCBA")
ORDERS_64 = ("ABCDEFGH", "GHEFCDAB", "BADCFEHG", "HGFEDCBA")
#: (words reversed, bytes swapped in each word) of each multi-byte order
_RULES = {
    **{o: (i & 1 == 1, i >= 2) for i, o in enumerate(ORDERS_32)},
    **{o: (i & 1 == 1, i >= 2) for i, o in enumerate(ORDERS_64)},
    "AB": (False, False),
    "BA": (False, True),
}


@dataclass(frozen=True, slots=True)
class Codec:
    """A register type: ``registers`` it takes (0: the point's ``count``, a string),
    ``kind`` of its values (``int``, ``float``, ``str``, ``bool``), the range of an
    integer type (``low``..``high``), its ``orders`` (the first the default) and
    the makers of its functions (see `decoder`, `encoder`)."""

    name: str
    registers: int
    kind: str
    orders: tuple[str, ...]
    make_decode: Callable[[str, int], Decode]
    make_encode: Callable[[str, int], Encode]
    low: int = 0
    high: int = 0


def _u16(reg: object) -> int:
    if isinstance(reg, bool) or not isinstance(reg, int) or not 0 <= reg <= 0xFFFF:
        raise ValueError(f"a register is 0..65535, not {reg!r}")
    return reg


def _swap16(reg: int) -> int:
    return (reg >> 8) | ((reg & 0xFF) << 8)


# ---------------------------------------------------------------- integers


def _check_int(name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        else:
            raise ValueError(f"a {name} must be an integer {lo}..{hi}, not {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"a {name} must be an integer {lo}..{hi}, not {value!r}")
    return value


def _packed_decode(value: struct.Struct, registers: int, reverse: bool, swap: bool) -> Decode:
    """A decoder through ``struct``: the ``registers`` words from ``b[i]`` (in reverse
    when ``reverse``, each word's bytes swapped when ``swap``) packed into the bytes of
    ``value``, and unpacked."""
    unpack = value.unpack
    pack = struct.Struct(f"{'<' if swap else '>'}{registers}H").pack
    if registers == 1:
        return lambda b, i: unpack(pack(b[i]))[0]
    if registers == 2:
        if reverse:
            return lambda b, i: unpack(pack(b[i + 1], b[i]))[0]
        return lambda b, i: unpack(pack(b[i], b[i + 1]))[0]
    if reverse:
        return lambda b, i: unpack(pack(b[i + 3], b[i + 2], b[i + 1], b[i]))[0]
    return lambda b, i: unpack(pack(b[i], b[i + 1], b[i + 2], b[i + 3]))[0]


def _int_codec(name: str, registers: int, signed: bool) -> Codec:
    bits = 16 * registers
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    top, wrap = 1 << (bits - 1), 1 << bits

    def make_decode(order: str, count: int) -> Decode:
        reverse, swap = _RULES[order]
        if registers == 1:
            if swap:
                if signed:
                    return lambda b, i: (_swap16(int(b[i])) ^ top) - top
                return lambda b, i: _swap16(int(b[i]))
            if signed:
                return lambda b, i: (int(b[i]) ^ top) - top
            return lambda b, i: int(b[i])
        if registers == 2 and not swap:
            if reverse:
                if signed:
                    return lambda b, i: ((b[i + 1] << 16 | b[i]) ^ top) - top
                return lambda b, i: b[i + 1] << 16 | b[i]
            if signed:
                return lambda b, i: ((b[i] << 16 | b[i + 1]) ^ top) - top
            return lambda b, i: b[i] << 16 | b[i + 1]
        letter = ("bhiq" if signed else "BHIQ")[registers.bit_length()]
        return _packed_decode(struct.Struct(">" + letter), registers, reverse, swap)

    def make_encode(order: str, count: int) -> Encode:
        reverse, swap = _RULES[order]

        def encode(value: Any) -> list[int]:
            v = _check_int(name, value, lo, hi) % wrap
            regs = [(v >> (16 * (registers - 1 - k))) & 0xFFFF for k in range(registers)]
            if swap:
                regs = [_swap16(r) for r in regs]
            return regs[::-1] if reverse else regs

        return encode

    orders = {1: ORDERS_16, 2: ORDERS_32, 4: ORDERS_64}[registers]
    return Codec(name, registers, "int", orders, make_decode, make_encode, lo, hi)


def _byte_codec(name: str, signed: bool) -> Codec:
    lo, hi = (-128, 127) if signed else (0, 255)

    def make_decode(order: str, count: int) -> Decode:
        shift = 8 if order == "high" else 0
        if signed:
            return lambda b, i: (((int(b[i]) >> shift) & 0xFF) ^ 0x80) - 0x80
        return lambda b, i: (int(b[i]) >> shift) & 0xFF

    def make_encode(order: str, count: int) -> Encode:
        shift = 8 if order == "high" else 0
        return lambda value: [(_check_int(name, value, lo, hi) & 0xFF) << shift]

    return Codec(name, 1, "int", ORDERS_8, make_decode, make_encode, lo, hi)


# ------------------------------------------------------------------ floats

#: the largest finite value of each float type
FLOAT_MAX = {
    "float16": 65504.0,
    "float32": 3.4028234663852886e38,
    "float64": 1.7976931348623157e308,
}


def _float_codec(name: str, registers: int) -> Codec:
    fmt = {1: "e", 2: "f", 4: "d"}[registers]
    value_struct = struct.Struct(">" + fmt)

    def make_decode(order: str, count: int) -> Decode:
        reverse, swap = _RULES[order]
        return _packed_decode(value_struct, registers, reverse, swap)

    def make_encode(order: str, count: int) -> Encode:
        reverse, swap = _RULES[order]
        regs_struct = struct.Struct(f"{'<' if swap else '>'}{registers}H")

        def encode(value: Any) -> list[int]:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"a {name} must be a number, not {value!r}")
            try:
                packed = value_struct.pack(value)
            except (OverflowError, struct.error):
                raise ValueError(
                    f"{value!r} is out of the {name} range (finite values up to"
                    f" ±{FLOAT_MAX[name]:.8g}; nan and ±inf are written as such)"
                ) from None
            regs = list(regs_struct.unpack(packed))
            return regs[::-1] if reverse else regs

        return encode

    orders = ORDERS_16 if registers == 1 else ORDERS_32 if registers == 2 else ORDERS_64
    return Codec(name, registers, "float", orders, make_decode, make_encode)


# --------------------------------------------------------------------- BCD


_BCD: list[int | None] = []


def _bcd_word(v: int) -> int | None:
    """A register's four BCD digits (None: a digit above 9), from a table built once."""
    if not _BCD:
        _BCD.extend(int(t) if (t := f"{w:04x}").isdigit() else None for w in range(0x10000))
    return _BCD[v]


def _bcd_codec(name: str, registers: int) -> Codec:
    digits = 4 * registers
    hi = 10**digits - 1

    def make_decode(order: str, count: int) -> Decode:
        reverse, swap = _RULES[order]
        _bcd_word(0)  # the table, now rather than in the first poll
        table = _BCD
        if swap:  # the table of the byte-swapped registers
            table = [_BCD[_swap16(w)] for w in range(0x10000)]
        if registers == 1:
            return lambda b, i: table[b[i]]
        first, second = (1, 0) if reverse else (0, 1)

        def decode32(b: Sequence[int], i: int) -> int | None:
            high, low = table[b[i + first]], table[b[i + second]]
            return None if high is None or low is None else high * 10000 + low

        return decode32

    def make_encode(order: str, count: int) -> Encode:
        reverse, swap = _RULES[order]

        def encode(value: Any) -> list[int]:
            v = _check_int(name, value, 0, hi)
            packed = int(f"{v:0{digits}d}", 16)
            regs = [(packed >> (16 * (registers - 1 - k))) & 0xFFFF for k in range(registers)]
            if swap:
                regs = [_swap16(r) for r in regs]
            return regs[::-1] if reverse else regs

        return encode

    return Codec(name, registers, "int", ORDERS_16 if registers == 1 else ORDERS_32,
                 make_decode, make_encode, 0, hi)  # fmt: skip


# ------------------------------------------------------------------ strings


def trim(raw: bytes) -> str:
    """Bytes read as text: cut at the first NUL, trailing spaces removed (Latin-1:
    every byte is a character)."""
    nul = raw.find(0)
    if nul >= 0:
        raw = raw[:nul]
    return raw.rstrip(b" ").decode("latin-1")


def text_bytes(name: str, value: object, capacity: int) -> bytes:
    """A text as the bytes a string type writes (Latin-1); ValueError when it is no
    string, has a character Latin-1 lacks or is longer than ``capacity``."""
    if not isinstance(value, str):
        raise ValueError(f"a {name} value must be a string, not {value!r}")
    try:
        raw = value.encode("latin-1")
    except UnicodeEncodeError as e:
        raise ValueError(f"{value!r}: {e.object[e.start]!r} is no Latin-1 character") from None
    if len(raw) > capacity:
        raise ValueError(
            f"{value!r} is {len(raw)} characters; its registers hold at most {capacity} characters"
        )
    return raw


def _string_codec(name: str, per_register: int) -> Codec:
    def make_decode(order: str, count: int) -> Decode:
        swap = order == "BA"
        if per_register == 2:

            def decode2(b: Sequence[int], i: int) -> str:
                raw = struct.pack(f"{'<' if swap else '>'}{count}H", *b[i : i + count])
                return trim(raw)

            return decode2
        words = struct.Struct(f">{count}H").pack
        first = 0 if swap else 1  # the byte of each register that holds the character

        return lambda b, i: trim(words(*b[i : i + count])[first::2])

    def make_encode(order: str, count: int) -> Encode:
        swap = order == "BA"

        def encode(value: Any) -> list[int]:
            raw = text_bytes(name, value, per_register * count).ljust(per_register * count, b"\0")
            if per_register == 1:
                return [c << 8 if swap else c for c in raw]
            return list(struct.unpack(f"{'<' if swap else '>'}{count}H", raw))

        return encode

    return Codec(name, 0, "str", ORDERS_16, make_decode, make_encode)


def _bool_decode(order: str, count: int) -> Decode:
    return lambda b, i: bool(b[i])


def _bool_encode(order: str, count: int) -> Encode:
    def encode(value: Any) -> list[int]:
        if not isinstance(value, bool | int) or value not in (0, 1):
            raise ValueError(f"a bool must be true or false (or 0/1), not {value!r}")
        return [int(value)]

    return encode


#: every register type, by name (see the module docstring)
CODECS: dict[str, Codec] = {
    c.name: c
    for c in (
        Codec("bool", 1, "bool", ORDERS_16, _bool_decode, _bool_encode, 0, 1),
        _byte_codec("int8", True),
        _byte_codec("uint8", False),
        _int_codec("int16", 1, True),
        _int_codec("uint16", 1, False),
        _int_codec("int32", 2, True),
        _int_codec("uint32", 2, False),
        _int_codec("int64", 4, True),
        _int_codec("uint64", 4, False),
        _float_codec("float16", 1),
        _float_codec("float32", 2),
        _float_codec("float64", 4),
        _bcd_codec("bcd16", 1),
        _bcd_codec("bcd32", 2),
        _string_codec("string", 2),
        _string_codec("string1", 1),
    )
}
TYPES = tuple(CODECS)
#: every order name, of every width
ORDERS = (*ORDERS_8, *ORDERS_16, *ORDERS_32, *ORDERS_64)
_EQUIVALENT = {**dict(zip(ORDERS_32, ORDERS_64, strict=True)),
               **dict(zip(ORDERS_64, ORDERS_32, strict=True))}  # fmt: skip


def codec(name: str) -> Codec:
    """The codec of type ``name``; ValueError naming the types when there is none."""
    try:
        return CODECS[name]
    except (KeyError, TypeError):
        raise ValueError(f"type must be one of {', '.join(TYPES)}, not {name!r}") from None


def normalize_order(name: str, order: str | None) -> str:
    """The order type ``name`` uses for ``order`` (see the module docstring; None
    or "": the type's default); ValueError naming the orders it takes."""
    c = codec(name)
    if order is None or order == "":
        return c.orders[0]
    if not isinstance(order, str):
        raise ValueError(f"order must be one of {', '.join(c.orders)}, not {order!r}")
    o = order if order in ORDERS_8 else order.upper()
    if o in c.orders:
        return o
    if (c.orders is ORDERS_64 and o in ORDERS_32) or (c.orders is ORDERS_32 and o in ORDERS_64):
        return _EQUIVALENT[o]
    if c.orders is ORDERS_16 and (o in ORDERS_32 or o in ORDERS_64):
        return "BA" if _RULES[o][1] else "AB"
    if c.orders is ORDERS_8 and (o in ORDERS_16 or o in ORDERS_32 or o in ORDERS_64):
        return c.orders[0]
    allowed = ", ".join(c.orders)
    if c.orders is ORDERS_64:
        allowed += " (or the 32-bit names ABCD, CDAB, BADC, DCBA)"
    raise ValueError(f"order of a {name} must be one of {allowed}, not {order!r}")


def size(name: str, count: int = 0) -> int:
    """Registers a value of type ``name`` takes (``count``: a string's)."""
    return codec(name).registers or count


def decoder(name: str, order: str | None = None, count: int = 0) -> Decode:
    """``decode(block, i)``: the value of type ``name`` at index ``i`` of ``block``."""
    c = codec(name)
    return c.make_decode(normalize_order(name, order), count)


def encoder(name: str, order: str | None = None, count: int = 0) -> Encode:
    """``encode(value)``: the registers of a value of type ``name`` (ValueError when
    the type cannot hold it)."""
    c = codec(name)
    return c.make_encode(normalize_order(name, order), count)


def decode(name: str, registers: Sequence[int], order: str | None = None) -> Value | None:
    """One value of type ``name`` from ``registers`` (all of them: a string's count)."""
    regs = [_u16(r) for r in registers]
    want = size(name, len(regs))
    if len(regs) != want or want == 0:
        raise ValueError(f"a {name} takes {want or 'at least 1'} registers, got {len(regs)}")
    return decoder(name, order, len(regs))(regs, 0)


def encode(name: str, value: object, order: str | None = None, count: int = 0) -> list[int]:
    """The registers of one value of type ``name`` (``count``: a string's registers;
    0: just long enough)."""
    if codec(name).registers == 0 and count == 0:
        per = 1 if name == "string1" else 2
        count = max(1, -(-len(text_bytes(name, value, 1 << 20)) // per))
    return encoder(name, order, count)(value)


# --------------------------------------------------------------- bit fields


def field_masks(first: int, width: int, value: int) -> tuple[int, int]:
    """(and_mask, or_mask) of FC 22 (Mask Write Register, Application Protocol 6.16:
    ``result = (current AND and_mask) OR (or_mask AND NOT and_mask)``) that set bits
    ``first`` .. ``first + width - 1`` of a register to ``value``."""
    if not 0 <= value < 1 << width:
        raise ValueError(f"a {width}-bit field holds 0..{(1 << width) - 1}, not {value!r}")
    mask = ((1 << width) - 1) << first
    return 0xFFFF & ~mask, (value << first) & mask


def apply_masks(register: int, and_mask: int, or_mask: int) -> int:
    """What FC 22 makes of ``register`` (a read-modify-write does the same)."""
    return (register & and_mask) | (or_mask & ~and_mask & 0xFFFF)


def is_nan(value: object) -> bool:
    return isinstance(value, float) and math.isnan(value)


__all__ = [
    "CODECS",
    "FLOAT_MAX",
    "ORDERS",
    "ORDERS_8",
    "ORDERS_16",
    "ORDERS_32",
    "ORDERS_64",
    "TYPES",
    "Codec",
    "Decode",
    "Encode",
    "Value",
    "apply_masks",
    "codec",
    "decode",
    "decoder",
    "encode",
    "encoder",
    "field_masks",
    "is_nan",
    "normalize_order",
    "size",
    "text_bytes",
    "trim",
]
