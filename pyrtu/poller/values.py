"""A point's value as JSON and MQTT carry it: the shortest decimal that is faithful
to the register (issue 27.12).

Decoding is exact arithmetic on binary floats: a float32 register holding 5.1 reads
as 5.099999904632568 (the float32 nearest 5.1, widened to a double), and a uint16
214 scaled by 0.1 as 21.400000000000002.  Both say more than the register holds.
`faithful_value` gives the number a reader means:

* float32: the shortest decimal (1 to 9 significant digits) that rounds back to the
  same float32 (`shortest_float32`): 5.1, and 3.4028235e38 for the largest float32;
* an integer type with a scale or offset: the value rounded to the decimals of its
  resolution, those of ``scale`` and ``offset`` (0.1: one decimal): 21.4;
* a float32 with a scale or offset: the shortest float32 decimal, then scaled in
  exact decimal arithmetic;
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
from functools import lru_cache

from .points import Point, Value

_FLOAT32 = struct.Struct(">f")
#: significant digits that always tell two float32 apart (FLT_DECIMAL_DIG)
FLOAT32_DIGITS = 9


def shortest_float32(x: float) -> float:
    """The decimal with the fewest significant digits that rounds to the same float32
    as ``x`` (a float32 widened to a double), as the double nearest it.  NaN, the
    infinities and a double beyond float32's range come back unchanged."""
    if not math.isfinite(x):
        return x
    try:
        bits = _FLOAT32.pack(x)
    except OverflowError:
        return x  # not a float32's value
    for digits in range(1, FLOAT32_DIGITS + 1):
        candidate = float(f"{x:.{digits}g}")
        try:
            if _FLOAT32.pack(candidate) == bits:
                return candidate
        except OverflowError:  # rounded up past the largest float32
            continue
    return x  # unreachable: 9 digits tell every float32 apart


def _exact(x: float) -> Decimal:
    """The decimal a configured number was written as (its shortest repr)."""
    return Decimal(repr(x))


@lru_cache(maxsize=1024)
def _decimals(scale: float, offset: float) -> int:
    """The decimals of the resolution of ``raw * scale + offset`` for an integer raw."""
    exponents = (_exact(v).normalize().as_tuple().exponent for v in (scale, offset) if v)
    return max([0, *(-e for e in exponents if isinstance(e, int))])


def faithful_value(point: Point, value: Value | None) -> Value | None:
    """``value``, decoded from ``point``'s registers, as its shortest faithful
    decimal (see the module docstring); None stays None."""
    if not isinstance(value, float) or not math.isfinite(value):
        return value
    scaled = point.scale != 1 or point.offset != 0
    if point.type == "float32":
        if not scaled:
            return shortest_float32(value)
        raw = shortest_float32((value - point.offset) / point.scale)
        if not math.isfinite(raw):
            return value
        return float(_exact(raw) * _exact(point.scale) + _exact(point.offset))
    if scaled:
        return round(value, _decimals(point.scale, point.offset))
    return value


__all__ = ["FLOAT32_DIGITS", "faithful_value", "shortest_float32"]
