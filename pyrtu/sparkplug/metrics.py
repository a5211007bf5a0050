"""A point as a Sparkplug metric (sans-I/O): its name, alias, datatype, value field
and properties; the devices of an edge node and their metrics.

The datatype follows from the point's type (`DATATYPES`): a point with an ``enum``
is a String (its label), one with a ``scale`` or ``offset`` other than 1 and 0 a
Double (its value is ``raw * scale + offset``), the rest its register type's.  A
metric's properties carry what the point's configuration knows: ``engUnit``
(String), ``engLow``/``engHigh`` (Double: its ``min``/``max``), ``writable``
(Boolean), ``readOnly`` and, in a data message whose value is not good, the
specification's ``Quality`` (Int32: 0 bad, 500 stale; 192 good is never sent, it
is the default).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from ..poller import Point
from ..poller.points import Value

# the DataType numbers of the specification (chapter 6, "Data Types")
INT8, INT16, INT32, INT64 = 1, 2, 3, 4
UINT8, UINT16, UINT32, UINT64 = 5, 6, 7, 8
FLOAT, DOUBLE, BOOLEAN, STRING = 9, 10, 11, 12

#: a point type -> its metric's datatype (before enum and scale)
DATATYPES = {
    "bool": BOOLEAN,
    "int8": INT8,
    "uint8": UINT8,
    "int16": INT16,
    "uint16": UINT16,
    "int32": INT32,
    "uint32": UINT32,
    "int64": INT64,
    "uint64": UINT64,
    "float16": FLOAT,
    "float32": FLOAT,
    "float64": DOUBLE,
    "bcd16": UINT16,
    "bcd32": UINT32,
    "string": STRING,
    "string1": STRING,
}
#: the ``Quality`` property's codes (chapter 6, "Quality Codes")
QUALITY = {"bad": 0, "good": 192, "stale": 500}
#: the bounds of each integer datatype (what a DCMD's value must fit)
INT_RANGES = {
    INT8: (-(2**7), 2**7 - 1),
    INT16: (-(2**15), 2**15 - 1),
    INT32: (-(2**31), 2**31 - 1),
    INT64: (-(2**63), 2**63 - 1),
    UINT8: (0, 2**8 - 1),
    UINT16: (0, 2**16 - 1),
    UINT32: (0, 2**32 - 1),
    UINT64: (0, 2**64 - 1),
}
NODE_REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"


def datatype(point: Point) -> int:
    """The datatype of ``point``'s metric (see the module docstring)."""
    if point.labels:
        return STRING
    if point.type != "bool" and (point.scale != 1 or point.offset != 0):
        return DOUBLE
    return DATATYPES[point.type]


def set_value(metric: Any, dtype: int, value: Value | None) -> None:
    """Put ``value`` into ``metric``'s value field for ``dtype`` (None: ``is_null``).
    Signed integers are stored as their two's complement in the unsigned field
    (``int_value`` 32 bits, ``long_value`` 64), as the specification says."""
    if value is None:
        metric.is_null = True
        return
    if dtype == BOOLEAN:
        metric.boolean_value = bool(value)
    elif dtype == STRING:
        metric.string_value = str(value)
    elif dtype == FLOAT:
        metric.float_value = float(value)
    elif dtype == DOUBLE:
        metric.double_value = float(value)
    elif dtype in (INT64, UINT64):
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    else:
        metric.int_value = int(value) & 0xFFFFFFFF


def get_value(metric: Any, dtype: int) -> object:
    """A command's value from ``metric`` for ``dtype``; ValueError saying why not
    (a value field that does not fit the datatype, a number outside its range)."""
    field = metric.WhichOneof("value")
    if metric.HasField("is_null") and metric.is_null:
        raise ValueError("a null value cannot be written")
    want = {
        BOOLEAN: "boolean_value",
        STRING: "string_value",
        FLOAT: "float_value",
        DOUBLE: "double_value",
        INT64: "long_value",
        UINT64: "long_value",
    }.get(dtype, "int_value")
    if field is None:
        raise ValueError("no value")
    if field != want:
        raise ValueError(f"a {_NAMES.get(dtype, dtype)} metric takes {want}, not {field}")
    raw = getattr(metric, field)
    if dtype in INT_RANGES:
        bits = 64 if want == "long_value" else 32
        lo, hi = INT_RANGES[dtype]
        value = raw - (1 << bits) if lo < 0 and raw >= 1 << (bits - 1) else raw
        if not lo <= value <= hi:
            raise ValueError(f"{value} is outside a {_NAMES[dtype]}'s range {lo}..{hi}")
        return int(value)
    if dtype in (FLOAT, DOUBLE) and not math.isfinite(raw):
        raise ValueError("the value must be a finite number")
    return raw


_NAMES = {
    INT8: "Int8", INT16: "Int16", INT32: "Int32", INT64: "Int64", UINT8: "UInt8",
    UINT16: "UInt16", UINT32: "UInt32", UINT64: "UInt64", FLOAT: "Float",
    DOUBLE: "Double", BOOLEAN: "Boolean", STRING: "String",
}  # fmt: skip


def add_property(props: Any, key: str, dtype: int, value: object) -> None:
    props.keys.append(key)
    pv = props.values.add()
    pv.type = dtype
    if dtype == BOOLEAN:
        pv.boolean_value = bool(value)
    elif dtype == STRING:
        pv.string_value = str(value)
    elif dtype == DOUBLE:
        pv.double_value = float(value)  # type: ignore[arg-type]
    else:
        pv.int_value = int(value) & 0xFFFFFFFF  # type: ignore[call-overload]


@dataclass(frozen=True, slots=True)
class MetricDef:
    """One point as a metric: ``name`` (the point's name without its device's
    prefix), ``alias`` (unique through the edge node), ``datatype``."""

    point: Point
    name: str
    alias: int
    datatype: int

    def birth_properties(self, metric: Any) -> None:
        p = self.point
        props = metric.properties
        if p.unit:
            add_property(props, "engUnit", STRING, p.unit)
        if p.min is not None:
            add_property(props, "engLow", DOUBLE, p.min)
        if p.max is not None:
            add_property(props, "engHigh", DOUBLE, p.max)
        add_property(props, "readOnly", BOOLEAN, not p.writable)


@dataclass(frozen=True, slots=True)
class DeviceDef:
    """One Modbus device (bus, slave) as a Sparkplug device ``id``."""

    id: str
    bus: str
    slave: int
    metrics: tuple[MetricDef, ...]
    template: str = ""


def check_id(what: str, value: object) -> str:
    """A Sparkplug id (group, edge node, device, host): a non-empty UTF-8 string
    without ``+``, ``/``, ``#`` (tck-id-topic-structure-namespace-valid-*)."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string")
    bad = sorted({c for c in value if c in "+/#" or ord(c) < 0x20 or c == "\x7f"})
    if bad:
        raise ValueError(
            f"{what} {value!r} holds {', '.join(map(repr, bad))} (no + / # or control characters)"
        )
    try:
        value.encode("utf-8")
    except UnicodeEncodeError as e:
        raise ValueError(f"{what} {value!r} is not valid UTF-8: {e.reason}") from None
    return value


def devices(
    points: Iterable[Point], names: dict[tuple[str, int], str], first_alias: int
) -> tuple[DeviceDef, ...]:
    """The devices of an edge node: one per (bus, slave) with points, in the order
    of their first point; ``names``: (bus, slave) -> the ``[[device]]``'s name
    (else ``{bus}-{slave}``).  Aliases are numbered from ``first_alias``."""
    grouped: dict[tuple[str, int], list[Point]] = {}
    for p in points:
        grouped.setdefault((p.bus, p.slave), []).append(p)
    out: list[DeviceDef] = []
    alias = first_alias
    seen: dict[str, tuple[str, int]] = {}
    for (bus, slave), pts in grouped.items():
        given = names.get((bus, slave), "")
        dev_id = check_id("device id", given or f"{bus}-{slave}")
        other = seen.get(dev_id.lower())
        if other is not None:
            raise ValueError(
                f"device id {dev_id!r} of bus {bus!r} slave {slave} is also that of bus "
                f"{other[0]!r} slave {other[1]} (device ids must differ, case aside)"
            )
        seen[dev_id.lower()] = (bus, slave)
        metrics = []
        lowered: dict[str, str] = {}  # a metric name in lower case -> the name
        for p in pts:
            name = p.name[len(given) + 1 :] if given and p.name.startswith(given + ".") else p.name
            twin = lowered.get(name.lower())
            if twin is not None:  # tck-id-case-sensitivity-metric-names
                raise ValueError(
                    f"device {dev_id!r}: metric names {twin!r} and {name!r} differ only in "
                    "case (a host may not tell them apart)"
                )
            lowered[name.lower()] = name
            metrics.append(MetricDef(p, name, alias, datatype(p)))
            alias += 1
        out.append(DeviceDef(dev_id, bus, slave, tuple(metrics)))
    return tuple(out)


__all__ = [
    "BDSEQ",
    "DATATYPES",
    "NODE_REBIRTH",
    "QUALITY",
    "DeviceDef",
    "MetricDef",
    "add_property",
    "check_id",
    "datatype",
    "devices",
    "get_value",
    "set_value",
]
