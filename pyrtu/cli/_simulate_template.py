"""``pyrtu simulate --template FILE``: any device template served as a slave.

`TemplateSimulator` keeps the template's points in a `DataStore`, each with its
initial value (the point's ``initial``, a ``--values`` file's, else zero, false
or an empty string), and answers as a real device of that model would:

* a read of a register or bit no point covers: exception 2 (ILLEGAL DATA
  ADDRESS), except inside the ``max_gap`` the template lets a read span (zeros);
* a write to a point that is not ``writable`` (or to a gap): exception 2;
* a written value outside the point's ``min``..``max``: exception 3 (ILLEGAL
  DATA VALUE), and nothing is stored;
* FC 43 answers the template's ``identify`` (else its vendor and model);
* only the template's ``functions`` (default: every standard one), after its
  ``response_delay``.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pyrtu.devices._simbase import DriveSimulator
from pyrtu.pdu.errors import SlaveException
from pyrtu.poller.config import ConfigError, template_points
from pyrtu.poller.points import Point, encode_point_value

if TYPE_CHECKING:
    from pyrtu.devices.registry import Template
    from pyrtu.poller.points import Value

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


def read_values(path: str | Path, points: Sequence[Point]) -> dict[str, Any]:
    """A ``--values`` file: TOML ``point_name = value`` lines (ConfigError naming
    the file, line and point when a name or value does not fit)."""
    from pyrtu.poller.config import read_config_text

    p = Path(path)
    text = read_config_text(p)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: {e}") from None
    by_name = {pt.name: pt for pt in points}

    def where(key: str) -> str:
        want = re.compile(r"""^\s*["']?""" + re.escape(key) + r"""["']?\s*=""")
        for n, line in enumerate(text.splitlines()):
            if want.match(line):
                return f"{p}:{n + 1}"
        return str(p)

    for key, value in doc.items():
        point = by_name.get(key)
        if point is None:
            raise ConfigError(f"{where(key)}: {key}: no such point (points: {', '.join(by_name)})")
        try:
            encode_point_value(_writable_copy(point), value)
        except ValueError as e:
            raise ConfigError(
                f"{where(key)}: {key}: {str(e).removeprefix(f'point {key!r}: ')}"
            ) from None
    return dict(doc)


def _writable_copy(point: Point) -> Point:
    from dataclasses import replace

    return replace(point, table="coils" if point.bit_table else "holding")


def _default(point: Point) -> Value:
    if point.type == "bool":
        return False
    if point.type == "string":
        return ""
    return point.offset  # raw zero


def _in_range(value: object, low: object, high: object) -> bool:
    if not isinstance(value, int | float) or isinstance(value, bool):
        return True
    if isinstance(value, float) and math.isnan(value):
        return low is None and high is None
    if isinstance(low, int | float) and value < low:
        return False
    return not (isinstance(high, int | float) and value > high)


#: the poller's table names -> the `DataStore`'s
STORE_TABLES = {"coils": "coils", "discrete_inputs": "discrete_inputs",
                "holding": "holding_registers", "input": "input_registers"}  # fmt: skip


class _Group:
    """Points sharing registers (aliases, bit fields of one register): one range."""

    def __init__(self, table: str, first: Point) -> None:
        self.table = table
        self.points = [first]
        self.start = first.address
        self.end = first.end

    def add(self, point: Point) -> None:
        self.points.append(point)
        self.end = max(self.end, point.end)


#: the points of the templates parsed lately, by id (the template kept: the id stays its)
_PARSED: dict[int, tuple[Template, list[Point], dict[str, dict[str, Any]], dict[str, Point]]] = {}


def _parsed(
    template: Template,
) -> tuple[list[Point], dict[str, dict[str, Any]], dict[str, Point]]:
    """`template_points` of ``template`` and each point's writable copy (what its
    initial value is encoded with), made once however many simulators it has
    (``--tcp HOST:FIRST-LAST``: one per port); the hints are only read."""
    got = _PARSED.get(id(template))
    if got is None or got[0] is not template:
        if len(_PARSED) >= 8:
            _PARSED.clear()
        points, hints = template_points(template)
        writable = {point.name: _writable_copy(point) for point in points}
        got = _PARSED[id(template)] = (template, points, hints, writable)
    return list(got[1]), got[2], got[3]


class TemplateSimulator(DriveSimulator):
    """A device template behind a `DataStore` (see the module docstring); ``values``
    (point name -> value) override the template's ``initial`` values."""

    def __init__(
        self, template: Template, values: Mapping[str, Any] | None = None, *, mode: str = "rtu"
    ) -> None:
        self.modes = template.modes
        super().__init__(mode=mode)
        self.template = template
        self.device = template.name
        self.example_addresses = frozenset({template.address})
        points, hints, self._writable = _parsed(template)
        self.points = points
        self.hints = hints
        initial = {p.name: hints[p.name].get("initial", _default(p)) for p in points}
        initial.update(values or {})
        self._build(initial)

    # -- the store ---------------------------------------------------------------------

    def _build(self, initial: Mapping[str, Any]) -> None:
        by_table: dict[str, list[Point]] = {}
        for p in self.points:
            by_table.setdefault(p.table, []).append(p)
        gap = self.template.limits.get("max_gap", 0)
        for table, members in by_table.items():
            members.sort(key=lambda p: (p.address, p.size))
            groups: list[_Group] = []
            for p in members:
                if groups and p.address < groups[-1].end:
                    groups[-1].add(p)
                else:
                    groups.append(_Group(table, p))
            store_table = self.store.table(STORE_TABLES[table])
            bits = table in ("coils", "discrete_inputs")
            for n, g in enumerate(groups):
                values: list[int | bool] = [False if bits else 0] * (g.end - g.start)
                for p in g.points:
                    words = encode_point_value(self._writable[p.name], initial[p.name]).words
                    values[p.address - g.start : p.end - g.start] = list(words)
                store_table.add_range(
                    g.start, values, validator=self._validator(g), on_write=self._on_write(g)
                )
                following = groups[n + 1].start if n + 1 < len(groups) else None
                if following is not None and 0 < following - g.end <= gap:
                    filler = [False if bits else 0] * (following - g.end)
                    store_table.add_range(g.end, filler, validator=_refuse)

    def _validator(self, group: _Group) -> Any:
        def check(address: int, value: object) -> bool:
            for p in group.points:
                if p.address <= address < p.end and self.hints[p.name].get("writable"):
                    return True
            raise SlaveException(2, f"{group.table} {address} is not writable")

        return check

    def _on_write(self, group: _Group) -> Any:
        table = self.store.table(STORE_TABLES[group.table])

        def written(address: int, values: list[Any]) -> None:
            end = address + len(values)
            block = table.get_many(group.start, group.end - group.start)
            for p in group.points:
                if p.end <= address or end <= p.address:
                    continue
                hint = self.hints[p.name]
                value = p.decode(block, group.start)
                if not _in_range(value, hint.get("min"), hint.get("max")):
                    raise SlaveException(
                        3,
                        f"{p.name}: {value!r} is outside {hint.get('min')}..{hint.get('max')}",
                    )

        return written

    def value(self, name: str) -> Value | None:
        """The present value of point ``name`` (as the template decodes it; None: the
        point's "no value" marker)."""
        for p in self.points:
            if p.name == name:
                table = self.store.table(STORE_TABLES[p.table])
                return p.decode(table.get_many(p.address, p.size), p.address)
        raise KeyError(name)

    def values(self) -> dict[str, Value | None]:
        """Every point's present value."""
        with self.lock:
            return {p.name: self.value(p.name) for p in self.points}

    # -- DriveSimulator ----------------------------------------------------------------

    def _retarget(self) -> None:
        """No motor: the values are the registers'."""

    def _refresh(self) -> None:
        """No model: the registers keep what was written."""

    def slave_options(self) -> dict[str, Any]:
        t = self.template
        options: dict[str, Any] = {
            "identification": t.identification(),
            "response_delay": t.response_delay,
            "mode": self.mode,
        }
        if t.functions is not None:
            options["functions"] = set(t.functions)
        if "max_adu" in t.limits and self.mode == "rtu":
            options["max_adu"] = t.limits["max_adu"]
        return options

    def describe(self) -> str:
        """The points' values, one line (``--watch``)."""
        return "  ".join(f"{k}={v}" for k, v in self.values().items())


def _refuse(address: int, value: object) -> bool:
    raise SlaveException(2, f"address {address} is a gap between points: not writable")


__all__ = ["TemplateSimulator", "read_values"]
