"""Points: named, typed values at a place in a slave's data model.

A point is a value a poller keeps fresh: where it is (bus, slave, table, address),
how its registers or bits become a value (type, word order, scale and offset) and
how often it is read (interval, in seconds) and reported (deadband)::

    Point("cfw701.speed", bus="line1", slave=1, table="holding", address=2,
          type="uint16", scale=0.1, interval=0.1, deadband=0.5)

Every field is checked when the point is made; a bad one raises `PointError`
(a ValueError) whose ``field`` names it and whose message says what is wrong.
Decoding and encoding use the register types of `pyrtu.pdu.codecs` (one table for
the poller, the CLI, `pyrtu.data` and the bridge); each point composes its decoder
once (its type, bit or field, "no value" markers, labels, scale).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from decimal import ROUND_HALF_UP, Decimal
from typing import Any

from pyrtu.devices.registry import STATE_CLASSES
from pyrtu.pdu import codecs
from pyrtu.pdu.codecs import CODECS, ORDERS_8, ORDERS_16, ORDERS_32

#: the four tables of the Modbus data model, as points name them
TABLES = ("coils", "discrete_inputs", "holding", "input")
BIT_TABLES = frozenset({"coils", "discrete_inputs"})
#: value types (`pyrtu.pdu.codecs.CODECS`); ``bool`` is the type of bit tables and
#: of a register's ``bit``, the others of register tables
TYPES = codecs.TYPES
#: the Home Assistant hints a point carries for the bridge's discovery
HA_KEYS = ("device_class", "state_class", "icon")

#: the 16-bit integer views of one register: its bytes, bits and fields may overlap them
_REGISTER_VIEWS = frozenset({"uint16", "int16", "uint8", "int8", "bool"})

Value = bool | int | float | str


class PointError(ValueError):
    """A point field with a wrong value; ``field`` names it."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.detail = message


def _int(field: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise PointError(field, f"must be an integer {lo}..{hi}, not {value!r}")
    if not lo <= value <= hi:
        raise PointError(field, f"must be {lo}..{hi}, not {value!r}")
    return value


def _number(field: str, value: object, *, positive: bool = False, minimum: float = 0) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PointError(field, f"must be a finite number, not {value!r}")
    if positive and value <= minimum:
        raise PointError(field, f"must be greater than {minimum:g}, not {value!r}")
    return float(value)


def _name(field: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise PointError(field, f"must be a non-empty string, not {value!r}")
    return value


def _text(field: str, value: object) -> str:
    if not isinstance(value, str):
        raise PointError(field, f"must be a string, not {value!r}")
    return value


def _enum(value: object, lo: int, hi: int) -> tuple[tuple[int, str], ...]:
    """``enum`` as (value, label) pairs: a table of value -> label (TOML's keys are
    strings: ``"0"``, ``"0x10"``) or an array of labels (value 0, 1, ...)."""
    if isinstance(value, Mapping):
        items = list(value.items())
    elif isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
        items = list(enumerate(value))
    elif isinstance(value, list | tuple):  # (value, label) pairs: a Point's own form
        items = [tuple(v) for v in value]
    else:
        raise PointError("enum", f"must be a table of value = label, not {value!r}")
    out: list[tuple[int, str]] = []
    for item in items:
        if len(item) != 2:
            raise PointError("enum", f"must be a table of value = label, not {value!r}")
        key, label = item
        if isinstance(key, str):
            try:
                key = int(key, 0)
            except ValueError:
                raise PointError(
                    "enum", f"{key!r} is no integer (keys are values: 0 = ...)"
                ) from None
        if isinstance(key, bool) or not isinstance(key, int) or not lo <= key <= hi:
            raise PointError("enum", f"value {key!r} is outside the point's {lo}..{hi}")
        if not isinstance(label, str) or not label:
            raise PointError(
                "enum", f"the label of {key} must be a non-empty string, not {label!r}"
            )
        if any(k == key for k, _ in out):
            raise PointError("enum", f"value {key} has two labels")
        if any(lab == label for _, lab in out):
            raise PointError("enum", f"label {label!r} names two values")
        out.append((key, label))
    if not out:
        raise PointError("enum", "must name at least one value")
    return tuple(out)


@dataclass(frozen=True, slots=True)
class Point:
    """A polled value (see the module docstring).

    ``type`` (`TYPES`, `pyrtu.pdu.codecs`) defaults to ``bool`` on the bit tables
    and on a register's ``bit``, ``uint16`` on the register tables; ``count`` is
    the register count of a string; ``order`` the word/byte order (default: the
    type's: ``ABCD``, ``ABCDEFGH``, ``AB``; 8-bit types: ``high`` or ``low``).
    Numbers are delivered as ``raw * scale + offset`` (integers stay integers while
    ``scale`` and ``offset`` are 1 and 0).  ``deadband``: a new value is delivered
    only when it differs from the last delivered one by more than this (0: any
    change).

    ``bit`` (0..15): one bit of a holding or input register (a bool); ``bits``
    ``(first, width)``: a field of it (an unsigned integer; ``int16``: signed).
    ``enum``: value -> label pairs; the label is the value delivered (a value
    without one is delivered as the number) and a write takes a label.
    ``error_value``/``unsupported_value``: the device's "no value" marker (the raw
    value, before scale; a signed type takes it as the register's pattern too,
    0x8000 for an int16; NaN for a float): decoded as None (quality ``bad``).
    ``writable``, ``min``, ``max``: what the bridge lets a set command write (the
    bounds apply to every write); ``unit``, ``precision`` (decimals to show),
    ``device_class``, ``state_class``, ``icon``: for Home Assistant's discovery.
    """

    name: str
    bus: str
    slave: int
    table: str
    address: int
    type: str = ""
    order: str = ""
    count: int = 0
    scale: float = 1.0
    offset: float = 0.0
    interval: float = 1.0
    deadband: float = 0.0
    unit: str = ""
    precision: int | None = None
    enum: Any = None
    bit: int | None = None
    bits: Any = None
    error_value: int | float | None = None
    unsupported_value: int | float | None = None
    writable: bool = False
    min: float | None = None
    max: float | None = None
    device_class: str = ""
    state_class: str = ""
    icon: str = ""
    _read: Callable[[Sequence[Any], int], Value | None] = field(
        init=False, repr=False, compare=False, default=lambda b, i: None
    )
    _plain: int = field(init=False, repr=False, compare=False, default=0)
    _size: int = field(init=False, repr=False, compare=False, default=1)
    _labels: Mapping[int, str] = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self) -> None:
        _name("name", self.name)
        _name("bus", self.bus)
        _int("slave", self.slave, 0, 255)
        if self.table not in TABLES:
            raise PointError("table", f"must be one of {', '.join(TABLES)}, not {self.table!r}")
        _int("address", self.address, 0, 0xFFFF)
        bit_table = self.table in BIT_TABLES
        if self.bit is not None or self.bits is not None:
            key = "bit" if self.bit is not None else "bits"
            if bit_table:
                raise PointError(key, f"applies to holding and input registers, not {self.table}")
            if self.bit is not None and self.bits is not None:
                raise PointError("bits", "give bit (one bit) or bits (a field), not both")
        kind = self.type or ("bool" if bit_table or self.bit is not None else "uint16")
        if kind not in CODECS:
            raise PointError("type", f"must be one of {', '.join(TYPES)}, not {self.type!r}")
        if bit_table and kind != "bool":
            raise PointError("type", f"the {self.table} table holds bool; got {kind!r}")
        if not bit_table and kind == "bool" and self.bit is None:
            raise PointError(
                "type",
                f"a bool of the {self.table} table is one bit of a register: give bit = 0..15",
            )
        if self.bit is not None and kind != "bool":
            raise PointError("type", f"a bit is a bool, not {kind!r}")
        object.__setattr__(self, "type", kind)
        codec = CODECS[kind]
        word = "uint16" if kind == "bool" and not bit_table else kind
        try:
            order = codecs.normalize_order(word, self.order)
        except ValueError:
            orders = CODECS[word].orders
            accepted = ", ".join(orders)
            if orders is ORDERS_16:
                accepted += " (or a 32- or 64-bit order: ABCD, CDAB, BADC, DCBA, ...)"
            elif orders is ORDERS_32:
                accepted += " (or the 64-bit names ABCDEFGH, GHEFCDAB, BADCFEHG, HGFEDCBA)"
            elif orders is not ORDERS_8:
                accepted += " (or the 32-bit names ABCD, CDAB, BADC, DCBA)"
            raise PointError("order", f"a {word} takes {accepted}, not {self.order!r}") from None
        object.__setattr__(self, "order", order)
        if codec.registers == 0:
            _int("count", self.count, 1, 125)
        elif self.count not in (0, self.size):
            raise PointError("count", f"applies to strings only ({kind} takes {self.size})")
        if self.address + self.size > 0x10000:
            raise PointError("address", f"{self.address} + {self.size} registers runs past 65535")
        field_lo, field_hi = codec.low, codec.high
        if self.bit is not None:
            _int("bit", self.bit, 0, 15)
        if self.bits is not None:
            b = self.bits
            if not isinstance(b, list | tuple) or len(b) != 2:
                raise PointError("bits", f"must be [first, width], not {b!r}")
            first = _int("bits", b[0], 0, 15)
            width = _int("bits", b[1], 1, 16 - first)
            object.__setattr__(self, "bits", (first, width))
            if kind not in ("uint16", "int16"):
                raise PointError("type", f"a bit field is a uint16 or int16, not {kind!r}")
            field_lo, field_hi = (
                (-(1 << (width - 1)), (1 << (width - 1)) - 1)
                if kind == "int16"
                else (0, (1 << width) - 1)
            )
        scale = _number("scale", self.scale)
        if scale == 0:
            raise PointError("scale", "must not be 0")
        _number("offset", self.offset)
        _number("interval", self.interval, positive=True)
        deadband = _number("deadband", self.deadband)
        if deadband < 0:
            raise PointError("deadband", f"must be >= 0, not {self.deadband!r}")
        number = codec.kind in ("int", "float")
        if not number and (scale != 1 or self.offset != 0):
            raise PointError("scale", f"a {kind} point takes no scale or offset")
        _text("unit", self.unit)
        for k in HA_KEYS:
            _text(k, getattr(self, k))
        if self.state_class and self.state_class not in STATE_CLASSES:
            raise PointError(
                "state_class",
                f"must be one of {', '.join(STATE_CLASSES)}, not {self.state_class!r}",
            )
        if self.precision is not None:
            _int("precision", self.precision, 0, 15)
        if not isinstance(self.writable, bool):
            raise PointError("writable", f"must be true or false, not {self.writable!r}")
        if self.writable and self.table not in ("holding", "coils"):
            raise PointError("writable", f"the {self.table} table is read only")
        labels: dict[int, str] = {}
        if self.enum is not None:
            if codec.kind not in ("int", "bool") or scale != 1 or self.offset != 0:
                raise PointError(
                    "enum",
                    f"applies to unscaled integers and bits, not a {kind}"
                    + (" with a scale or offset" if number and codec.kind == "int" else ""),
                )
            lo, hi = (0, 1) if kind == "bool" else (field_lo, field_hi)
            pairs = _enum(self.enum, lo, hi)
            object.__setattr__(self, "enum", pairs)
            labels = dict(pairs)
        object.__setattr__(self, "_labels", labels)
        for k in ("min", "max"):
            v = getattr(self, k)
            if v is None:
                continue
            if not number or labels:
                raise PointError(k, f"a {'enum' if labels else kind} point has no range")
            _number(k, v)
        if self.min is not None and self.max is not None and self.min > self.max:
            raise PointError("max", f"must be at least min ({self.min}), not {self.max!r}")
        for k in ("error_value", "unsupported_value"):
            v = getattr(self, k)
            if v is not None:
                object.__setattr__(self, k, self._marker(k, v, codec.kind, field_lo, field_hi))
        object.__setattr__(self, "_read", self._reader(word))
        object.__setattr__(self, "_size", self.size)
        plain = (self.scale == 1 and self.offset == 0 and self.bits is None and not labels
                 and self.error_value is None and self.unsupported_value is None)  # fmt: skip
        code = {"uint16": 1, "int16": 2, "bool": 3}.get(kind, 0) if plain else 0
        if (kind in ("uint16", "int16") and order != "AB") or (kind == "bool" and not bit_table):
            code = 0
        object.__setattr__(self, "_plain", code)

    def _marker(self, key: str, v: object, kind: str, lo: int, hi: int) -> int | float:
        if kind == "float":
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise PointError(key, f"must be a number (or nan), not {v!r}")
            return float(v)
        if kind not in ("int",):
            raise PointError(key, f"applies to numbers, not a {self.type}")
        if isinstance(v, bool) or not isinstance(v, int):
            raise PointError(key, f"must be an integer {lo}..{hi}, not {v!r}")
        if v > hi and lo < 0 and v <= 2 * hi + 1:  # a signed type's register pattern
            v -= 2 * (hi + 1)
        if not lo <= v <= hi:
            raise PointError(key, f"must be {lo}..{hi} (the raw value), not {v!r}")
        return v

    def _reader(self, word: str) -> Callable[[Sequence[Any], int], Value | None]:
        """The point's decoding, composed once: the type's, then its bit or field,
        its markers, its labels, its scale."""
        if self.table in BIT_TABLES:
            return lambda b, i: bool(b[i])
        read: Callable[[Sequence[Any], int], Any] = codecs.decoder(word, self.order, self.count)
        direct = word == "uint16" and self.order == "AB"  # the register as it is: inline
        markers = [m for m in (self.error_value, self.unsupported_value) if m is not None]
        if direct and self.bit is not None and not self._labels:
            n = self.bit
            return lambda b, i: bool(b[i] >> n & 1)
        if direct and self.bits is not None and self.type == "uint16" and not markers:
            first, width = self.bits
            mask = (1 << width) - 1
            if not self._labels:
                return lambda b, i: b[i] >> first & mask
            labels0 = self._labels
            return lambda b, i: labels0.get(v := b[i] >> first & mask, v)
        if direct and self.bits is None and self.type == "uint16" and self.scale == 1:
            if self.offset == 0 and not markers and self._labels:
                labels1 = self._labels
                return lambda b, i: labels1.get(v := b[i], v)
            if self.offset == 0 and markers and not self._labels:
                marks0 = frozenset(markers)
                return lambda b, i: None if (v := b[i]) in marks0 else v
        if self.bit is not None:
            n, inner = self.bit, read
            read = lambda b, i: bool((inner(b, i) >> n) & 1)  # noqa: E731
        elif self.bits is not None:
            first, width = self.bits
            mask, inner = (1 << width) - 1, read
            if self.type == "int16":
                sign = 1 << (width - 1)
                read = lambda b, i: ((((inner(b, i) & 0xFFFF) >> first) & mask) ^ sign) - sign  # noqa: E731
            else:
                read = lambda b, i: (inner(b, i) >> first) & mask  # noqa: E731
        if markers:
            inner2 = read
            if any(isinstance(m, float) and math.isnan(m) for m in markers):
                finite = [m for m in markers if not math.isnan(m)]

                def read_nan(b: Sequence[Any], i: int) -> Any:
                    v = inner2(b, i)
                    return None if v != v or v in finite else v  # v != v: NaN

                read = read_nan
            else:
                marks = frozenset(markers)
                read = lambda b, i: None if (v := inner2(b, i)) in marks else v  # noqa: E731
        if self._labels:
            labels, inner3 = self._labels, read

            def read_label(b: Sequence[Any], i: int) -> Any:
                v = inner3(b, i)
                return v if v is None else labels.get(int(v), v)

            read = read_label
        elif self.scale != 1 or self.offset != 0:
            scale, offset, inner4 = self.scale, self.offset, read

            def read_scaled(b: Sequence[Any], i: int) -> Any:
                v = inner4(b, i)
                return v if v is None else v * scale + offset

            read = read_scaled
        return read

    @property
    def bit_table(self) -> bool:
        """True on the bit tables (coils, discrete inputs)."""
        return self.table in BIT_TABLES

    @property
    def size(self) -> int:
        """Registers (or bits) the point takes."""
        return CODECS[self.type].registers or self.count

    @property
    def end(self) -> int:
        """One past the point's last register (or bit)."""
        return self.address + self.size

    @property
    def labels(self) -> tuple[str, ...]:
        """The enum's labels (none: no enum)."""
        return tuple(self._labels.values())

    def decode(self, block: Sequence[int] | Sequence[bool], start: int) -> Value | None:
        """The point's value in ``block``, the registers (or bits) read from address
        ``start`` (which must cover the point); None when the device said "no value"
        (its ``error_value`` or ``unsupported_value``, a BCD digit above 9)."""
        i = self.address - start
        plain = self._plain
        if plain and 0 <= i < len(block):
            # the common cases inline, without a call (measured in bench_decode)
            if plain == 1:
                return int(block[i])
            if plain == 3:
                return bool(block[i])
            v = int(block[i])
            return v - 0x10000 if v & 0x8000 else v
        if i < 0 or i + self._size > len(block):
            raise ValueError(
                f"point {self.name!r} ({self.address}..{self.end - 1}) is outside the "
                f"block {start}..{start + len(block) - 1}"
            )
        return self._read(block, i)

    def changed(self, old: Value | None, new: Value | None) -> bool:
        """Whether ``new`` is to be delivered after ``old`` (None: nothing yet, or no
        value)."""
        if old is None or new is None or type(old) is not type(new):
            return old is not new
        if isinstance(new, bool | str) or self.deadband == 0:
            if isinstance(new, float) and isinstance(old, float):
                return not (new == old or (math.isnan(new) and math.isnan(old)))
            return new != old
        assert isinstance(old, int | float) and isinstance(new, int | float)
        if math.isnan(new) != math.isnan(old):
            return True
        return abs(new - old) > self.deadband


def overlap_problem(a: Point, b: Point) -> str | None:
    """Why points ``a`` and ``b`` cannot share registers (None: they can, or do not
    share any): overlapping points must cover the same registers as the same type
    and order, or be 16-bit integer views of one register (its bytes, bits, fields,
    uint16, int16)."""
    if (a.bus, a.slave, a.table) != (b.bus, b.slave, b.table) or a.bit_table:
        return None
    if a.end <= b.address or b.end <= a.address:
        return None
    if a.address == b.address and a.size == b.size:
        if (a.type, a.order) == (b.type, b.order) and a.count == b.count:
            return None
        views = a.size == 1 and a.type in _REGISTER_VIEWS and b.type in _REGISTER_VIEWS
        orders = {o for o in (a.order, b.order) if o not in ORDERS_8}
        if views and len(orders) <= 1:
            return None
    return (
        f"registers {b.address}..{b.end - 1} ({b.type} {b.order}) overlap point {a.name!r}'s"
        f" {a.address}..{a.end - 1} ({a.type} {a.order}): points sharing registers must"
        " be the same registers of the same type and order, or bits, bytes and 16-bit"
        " integers of one register"
    )


class RegisterIndex:
    """The points of one table (of one slave) by address: which earlier points share
    registers with a new one, found without comparing it to every point (a
    configuration of thousands of points is checked in linear time, not quadratic)."""

    def __init__(self) -> None:
        self._starts: list[int] = []  # sorted
        self._entries: list[tuple[int, int, Point]] = []  # (start, rank, point), as _starts
        self._widest = 0

    def add(self, rank: int, point: Point) -> None:
        """Note ``point``, the ``rank``-th of its configuration."""
        at = bisect.bisect_right(self._starts, point.address)
        self._starts.insert(at, point.address)
        self._entries.insert(at, (point.address, rank, point))
        self._widest = max(self._widest, point.size)

    def overlapping(self, point: Point) -> list[tuple[int, Point]]:
        """The points noted before that share a register with ``point``, as
        (rank, point) in the order they were noted."""
        low = bisect.bisect_left(self._starts, point.address - self._widest + 1)
        high = bisect.bisect_left(self._starts, point.end)
        found = [
            (rank, other)
            for _start, rank, other in self._entries[low:high]
            if other.end > point.address
        ]
        return sorted(found, key=lambda entry: entry[0])


def check_unique(points: Sequence[Point]) -> None:
    """ValueError naming the first duplicated point name."""
    seen: set[str] = set()
    for p in points:
        if p.name in seen:
            raise PointError("name", f"{p.name!r} is declared twice")
        seen.add(p.name)


def encode_point(point: Point, value: object) -> list[int] | list[bool]:
    """The registers (or bits) that write ``value`` to ``point`` (the inverse of its
    scale and offset); ValueError when they cannot hold it (see `encode_point_value`);
    a bit or field of a register has no registers of its own (`Encoded.mask`)."""
    encoded = encode_point_value(point, value)
    if encoded.mask is not None:
        raise ValueError(
            f"point {point.name!r}: a bit or field is written with a mask (Encoded.mask)"
        )
    return encoded.words


@dataclass(frozen=True, slots=True)
class Encoded:
    """A value as a point's registers hold it: ``words`` to write, ``value`` what
    they hold in the point's units (the shortest decimal of ``raw * scale +
    offset``; an enum's label), ``rounded`` when that is not the value asked for (a
    scaled point, rounded to its resolution ``abs(scale)``).  A ``bit`` or ``bits``
    point's ``mask`` is (and_mask, or_mask) of FC 22 (Mask Write Register), its
    ``words`` empty: the other bits of the register are kept."""

    words: list[int] | list[bool]
    value: Value
    rounded: bool = False
    mask: tuple[int, int] | None = None


def _decimal(x: float) -> Decimal:
    """The decimal a number was written as (``0.1``, not its binary expansion)."""
    return Decimal(x) if isinstance(x, int) else Decimal(repr(x))


def _bounds(point: Point) -> str:
    lo = "" if point.min is None else f"{point.min:g}"
    hi = "" if point.max is None else f"{point.max:g}"
    return f"{lo}..{hi}"


def _field_range(point: Point) -> tuple[int, int]:
    if point.bits is None:
        c = CODECS[point.type]
        return c.low, c.high
    width = point.bits[1]
    if point.type == "int16":
        return -(1 << (width - 1)), (1 << (width - 1)) - 1
    return 0, (1 << width) - 1


def encode_point_value(point: Point, value: object) -> Encoded:
    """The registers that write ``value`` to ``point`` and what they hold.

    One rule for every writer (`Poller.write`, the bridge's set commands): an
    integer register takes ``value`` only when it holds it exactly, so on a point
    with ``scale`` 1 ``(value - offset)`` must be a whole number (1.5 is refused,
    never rounded to 2); a scaled point rounds to its resolution (``abs(scale)``,
    half away from zero, on the decimals as written: 21.45 at 0.1 is raw 215) and
    says so (`Encoded.rounded`).  A float takes the nearest of its type.  An enum
    takes one of its labels (or a value that has one); ``min``/``max`` bound every
    number; a string must fit its registers.  ValueError, naming the point and
    what it takes, when the value does not fit: nothing is sent."""
    name = point.name
    if point.table not in ("holding", "coils"):
        raise ValueError(f"point {name!r}: the {point.table} table is read only")
    if point._labels:
        labels = point._labels
        if isinstance(value, str):
            raw = next((k for k, lab in labels.items() if lab == value), None)
        elif not isinstance(value, bool) and isinstance(value, int) and value in labels:
            raw = value
        else:
            raw = None
        if raw is None:
            raise ValueError(
                f"point {name!r}: {value!r} is not one of its labels"
                f" ({', '.join(repr(lab) for lab in labels.values())})"
            )
        enc = _encode_raw(point, raw)
        return Encoded(enc.words, labels[raw], False, enc.mask)
    if point.type == "bool":
        if not isinstance(value, bool | int) or value not in (0, 1):
            raise ValueError(f"point {name!r}: value must be a bool (true or false), not {value!r}")
        if point.bit_table:
            return Encoded([bool(value)], bool(value))
        return _encode_raw(point, int(value), bool(value))
    if CODECS[point.type].kind == "str":
        try:
            words = codecs.encoder(point.type, point.order, point.count)(value)
        except ValueError as e:
            raise ValueError(f"point {name!r}: {e}") from None
        assert isinstance(value, str)
        return Encoded(words, value)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"point {name!r}: value must be a finite number, not {value!r}")
    if (point.min is not None and value < point.min) or (
        point.max is not None and value > point.max
    ):
        raise ValueError(f"point {name!r}: {value!r} is outside its min..max ({_bounds(point)})")
    if CODECS[point.type].kind == "float":
        raw_f = (value - point.offset) / point.scale
        try:
            words = codecs.encoder(point.type, point.order)(raw_f)
        except ValueError as e:
            raise ValueError(f"point {name!r}: {e}") from None
        return Encoded(words, value)
    lo, hi = _field_range(point)
    approx = (value - point.offset) / point.scale
    if not lo - 1 <= approx <= hi + 1:
        raise ValueError(f"point {name!r}: {value!r} is raw {approx:.6g}, outside {lo}..{hi}")
    raw_d = (_decimal(value) - _decimal(point.offset)) / _decimal(point.scale)
    n = int(raw_d.to_integral_value(rounding=ROUND_HALF_UP))
    if not lo <= n <= hi:
        raise ValueError(f"point {name!r}: {value!r} is raw {n}, outside {lo}..{hi}")
    rounded = raw_d != n
    if rounded and point.scale == 1:
        minus = "" if point.offset == 0 else f" minus the offset {point.offset!r}"
        raise ValueError(
            f"point {name!r}: {value!r}{minus} is not a whole number; "
            f"the {point.type} register holds whole numbers only"
        )
    held: Value = n
    if point.scale != 1 or point.offset != 0:
        held = float(n * _decimal(point.scale) + _decimal(point.offset))
    enc = _encode_raw(point, n)
    return Encoded(enc.words, held, rounded, enc.mask)


def _encode_raw(point: Point, raw: int, held: Value | None = None) -> Encoded:
    """A raw integer as the point's registers, or as the mask of its bit or field."""
    shown: Value = raw if held is None else held
    if point.bit is not None or point.bits is not None:
        first, width = (point.bit, 1) if point.bit is not None else point.bits
        and_mask, or_mask = codecs.field_masks(first, width, raw & ((1 << width) - 1))
        if point.order == "BA":  # the register's bytes are swapped on the wire
            and_mask, or_mask = (and_mask >> 8 | (and_mask & 0xFF) << 8,
                                 or_mask >> 8 | (or_mask & 0xFF) << 8)  # fmt: skip
        return Encoded([], shown, False, (and_mask, or_mask))
    try:
        words = codecs.encoder(point.type, point.order, point.count)(raw)
    except ValueError as e:
        raise ValueError(f"point {point.name!r}: {e}") from None
    return Encoded(words, shown)


__all__ = [
    "BIT_TABLES",
    "HA_KEYS",
    "TABLES",
    "TYPES",
    "Encoded",
    "Point",
    "PointError",
    "RegisterIndex",
    "Value",
    "check_unique",
    "encode_point",
    "encode_point_value",
    "overlap_problem",
]
