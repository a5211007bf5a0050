"""A point's value as JSON and MQTT carry it: the shortest decimal that is faithful
to the register (issue 27.12).

Decoding is exact arithmetic on binary floats: a float32 register holding 5.1 reads
as 5.099999904632568 (the float32 nearest 5.1, widened to a double), and a uint16
214 scaled by 0.1 as 21.400000000000002.  Both say more than the register holds.
`faithful_value` gives the number a reader means:

* float32: the shortest decimal (1 to 9 significant digits) that rounds back to the
  same float32 (`shortest_float32`): 5.1, and 3.4028235e38 for the largest float32;
  a float16 likewise (`shortest_float16`, 1 to 5 digits); a float64 as Python writes
  it (its shortest already);
* an integer type with a scale or offset: ``raw * scale + offset`` in exact decimal
  arithmetic, so at the resolution of ``scale`` and ``offset`` (0.1: one decimal):
  21.4;
* a float with a scale or offset: its shortest decimal, then scaled in exact
  decimal arithmetic;
* everything else (integers as read, bools, strings) as it is.

NaN and the infinities (a float32 register can hold them) are returned as they
are: JSON has no such numbers, each output says what it writes instead (the
bridge's payload ``null``, ``pyrtu poll --json`` the strings ``"nan"``, ``"inf"``,
``"-inf"``).  The returned float is the double nearest that decimal, so Python's
``repr`` (and `json.dumps`) writes exactly that decimal.
"""

from __future__ import annotations

import math
import struct
from decimal import Decimal

from pyrtu.pdu.codecs import CODECS

from .points import Point, Value

_FLOAT32 = struct.Struct(">f")
_FLOAT16 = struct.Struct(">e")
#: significant digits that always tell two float32 apart (FLT_DECIMAL_DIG)
FLOAT32_DIGITS = 9
#: the same for float16 (binary16's decimal digits)
FLOAT16_DIGITS = 5


def _shortest(x: float, form: struct.Struct, most: int) -> float:
    if not math.isfinite(x):
        return x
    try:
        bits = form.pack(x)
    except OverflowError:
        return x  # not a value of this width
    for digits in range(1, most + 1):
        candidate = float(f"{x:.{digits}g}")
        try:
            if form.pack(candidate) == bits:
                return candidate
        except OverflowError:  # rounded up past the largest value
            continue
    return x  # unreachable: ``most`` digits tell every value apart


def shortest_float32(x: float) -> float:
    """The decimal with the fewest significant digits that rounds to the same float32
    as ``x`` (a float32 widened to a double), as the double nearest it.  NaN, the
    infinities and a double beyond float32's range come back unchanged."""
    return _shortest(x, _FLOAT32, FLOAT32_DIGITS)


def shortest_float16(x: float) -> float:
    """`shortest_float32` for a float16 (0.1 for the half nearest 0.1)."""
    return _shortest(x, _FLOAT16, FLOAT16_DIGITS)


#: the narrow float types and their shortest decimals
_NARROW = {"float32": (_FLOAT32, shortest_float32), "float16": (_FLOAT16, shortest_float16)}
#: the integer types, whose scaled values are exact decimals
_INTEGERS = frozenset(n for n, c in CODECS.items() if c.kind == "int")


def _exact(x: float) -> Decimal:
    """The decimal a configured number was written as (its shortest repr)."""
    return Decimal(repr(x))


#: how far from an integer a raw value recovered from a scaled one may be (in raw
#: units, relative to the larger of the raw value and the offset): the rounding
#: error of ``raw * scale + offset`` and back is some 1e-16 of it
_ON_GRID = 1e-6


def _scaled_integer(point: Point, value: float) -> float:
    """``raw * scale + offset`` in exact decimal arithmetic, ``raw`` the integer the
    register held: the value at the resolution of the scale and the offset."""
    raw_float = (value - point.offset) / point.scale
    raw = round(raw_float)
    if abs(raw_float - raw) > _ON_GRID * max(1.0, abs(raw_float), abs(point.offset / point.scale)):
        return value  # not a value of this point's registers: as it is
    return float(raw * _exact(point.scale) + _exact(point.offset))


def faithful_value(point: Point, value: Value | None) -> Value | None:
    """``value``, decoded from ``point``'s registers, as its shortest faithful
    decimal (see the module docstring); None stays None, and so does a value the
    point's registers cannot hold (it came from elsewhere: nothing is made up)."""
    if not isinstance(value, float) or not math.isfinite(value):
        return value
    scaled = point.scale != 1 or point.offset != 0
    if point.type in _NARROW:
        form, shortest = _NARROW[point.type]
        raw = (value - point.offset) / point.scale if scaled else value
        try:
            if form.unpack(form.pack(raw))[0] != raw and not scaled:
                return value  # not a value of this width: as it is
        except OverflowError:
            return value
        short = shortest(raw)
        if not scaled:
            return short
        return float(_exact(short) * _exact(point.scale) + _exact(point.offset))
    if scaled and point.type == "float64":  # its repr is its shortest decimal already
        raw = (value - point.offset) / point.scale
        return float(_exact(raw) * _exact(point.scale) + _exact(point.offset))
    if scaled and point.type in _INTEGERS:
        return _scaled_integer(point, value)
    return value


__all__ = [
    "FLOAT16_DIGITS",
    "FLOAT32_DIGITS",
    "faithful_value",
    "shortest_float16",
    "shortest_float32",
]
