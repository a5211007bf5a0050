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

Points that share a register (``bit`` and ``bits`` fields, the two bytes of
8-bit types, aliases) keep each other's bits; of aliases, the value given
(``initial`` or ``--values``) is the registers'.

With ``vary`` (``pyrtu simulate --vary SECONDS``) the measured values change: step
``k`` begins ``k * SECONDS`` after the simulator started (step 0: the initial
values), and at each step every point a client cannot write (not ``writable``;
the input registers and discrete inputs) takes the next value of a ramp, `VaryPlan`:

* a number goes up by one unit of its register (one count; ``scale`` in the
  point's units), from its initial value, within ``min``..``max`` (where the
  template gives them) and what its register or field holds, wrapping from the
  top to the bottom (a float counts whole numbers, 0..65535 without bounds);
* a bool toggles; an ``enum`` point takes its next value (in the template's
  order, wrapping);
* a string, a point whose range holds one value, and an alias of a writable
  point's registers keep their values.

The values are brought to the present step when a request arrives (and for
``--watch``), so a client sees every step it reads after; they are computed once
per step for all the simulators of one template (``--tcp HOST:FIRST-LAST``: a
thousand devices step together).
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections.abc import Mapping, Sequence
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pyrtu.devices._simbase import DriveSimulator
from pyrtu.pdu.codecs import CODECS, apply_masks
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
    (point name -> value) override the template's ``initial`` values; ``vary``
    (seconds): the measured values take a step of their ramps every ``vary``
    seconds (`VaryPlan`)."""

    def __init__(
        self,
        template: Template,
        values: Mapping[str, Any] | None = None,
        *,
        mode: str = "rtu",
        vary: float | None = None,
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
        given = {p.name for p in points if "initial" in hints[p.name]} | set(values or {})
        self._given = given
        self._build(initial, given)
        self._vary = None if vary is None else vary_plan(self, initial, vary)
        self._vary_step = 0

    # -- the store ---------------------------------------------------------------------

    def _build(self, initial: Mapping[str, Any], given: set[str]) -> None:
        """The store's ranges, each point's initial value in its registers (where
        points share registers, the values given last: an alias without one keeps
        its sibling's)."""
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
                for p in sorted(g.points, key=lambda p: p.name in given):
                    enc = encode_point_value(self._writable[p.name], initial[p.name])
                    i = p.address - g.start
                    keep = 0xFFFF & ~_field_mask(p)  # the register's bits of other points
                    if enc.mask is not None:  # a bit or field: the register's other bits kept
                        values[i] = apply_masks(int(values[i]), *enc.mask)
                    elif keep and not p.bit_table:  # a byte
                        values[i] = int(values[i]) & keep | int(enc.words[0]) & ~keep
                    else:
                        values[i : p.end - g.start] = list(enc.words)
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
            self._refresh()
            return {p.name: self.value(p.name) for p in self.points}

    # -- DriveSimulator ----------------------------------------------------------------

    def _retarget(self) -> None:
        """No motor: the values are the registers'."""

    def _refresh(self) -> None:
        """No model: the registers keep what was written; with ``vary``, the
        measured values of the present step (`VaryPlan`)."""
        plan = self._vary
        if plan is None:
            return
        k = plan.step_now()
        if k != self._vary_step:
            self._vary_step = k
            store = self.store
            for table, pairs, masks in plan.writes(k):
                t = store.table(table)
                if pairs:
                    t.set_each(pairs)
                for address, and_mask, or_mask in masks:
                    t.set(address, apply_masks(int(t.get(address)), and_mask, or_mask))

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


class _Ramp:
    """One varied point: its values, step by step (see `VaryPlan`)."""

    def __init__(self, point: Point, writable: Point, values: list[Value], first: int) -> None:
        self.point = point
        self.writable = writable  # what the values are encoded with
        self.values = values  # the cycle when it is short (an enum, a bool) ...
        self.first = first  # ... its index of the initial value
        self.low = self.high = self.raw0 = 0  # ... else the raw range (values empty)

    def value(self, k: int) -> Value:
        if self.values:
            return self.values[(self.first + k) % len(self.values)]
        p, n = self.point, self.high - self.low + 1
        raw = self.low + (self.raw0 - self.low + k) % n
        if p.scale == 1 and p.offset == 0:
            return float(raw) if CODECS[p.type].kind == "float" else raw
        return float(raw * _decimal(p.scale) + _decimal(p.offset))


def _decimal(x: float) -> Decimal:
    return Decimal(x) if isinstance(x, int) else Decimal(repr(x))


def _shared(a: Point, b: Point) -> bool:
    """Whether points ``a`` and ``b`` hold a bit of one register or bit in common."""
    if a.table != b.table or a.end <= b.address or b.end <= a.address:
        return False
    return bool(_field_mask(a) & _field_mask(b))


def _field_mask(p: Point) -> int:
    """The bits of its register a one-register point holds (0xFFFF: all of them)."""
    if p.bit is not None:
        return 1 << p.bit
    if p.bits is not None:
        first, width = p.bits
        return int(((1 << width) - 1) << first)
    if p.type in ("int8", "uint8"):  # one byte of the register
        return 0xFF00 if (p.order or "high") == "high" else 0x00FF
    return 0xFFFF


def _ramp(point: Point, writable: Point, hint: Mapping[str, Any], initial: Any) -> _Ramp | None:
    """The ramp of a measured point (None: it keeps its value; see the module docstring)."""
    if point.enum:
        keys: list[Value] = [key for key, _label in point.enum]
        labels = [label for _key, label in point.enum]
        first = keys.index(initial) if initial in keys else labels.index(initial) if (
            initial in labels) else 0  # fmt: skip
        return _Ramp(point, writable, keys, first) if len(keys) > 1 else None
    if point.type == "bool":
        return _Ramp(point, writable, [False, True], 1 if initial else 0)
    kind = CODECS[point.type].kind
    if kind not in ("int", "float"):
        return None  # a string keeps its value
    if point.bits is not None:
        width = point.bits[1]
        signed = point.type == "int16"
        low = -(1 << (width - 1)) if signed else 0
        high = (1 << (width - 1)) - 1 if signed else (1 << width) - 1
    elif kind == "int":
        low, high = CODECS[point.type].low, CODECS[point.type].high
    else:
        low, high = 0, 0xFFFF
    scale, offset = _decimal(point.scale), _decimal(point.offset)
    bounds = [(_decimal(hint[k]) - offset) / scale for k in ("min", "max") if k in hint]
    if "min" in hint:
        raw = bounds[0]
        low, high = (
            (max(low, math.ceil(raw)), high) if scale > 0 else (low, min(high, math.floor(raw)))
        )
    if "max" in hint:
        raw = bounds[-1]
        low, high = (
            (low, min(high, math.floor(raw))) if scale > 0 else (max(low, math.ceil(raw)), high)
        )
    if high <= low:
        return None  # one value: nothing to vary
    ramp = _Ramp(point, writable, [], 0)
    ramp.low, ramp.high = low, high
    try:  # the ends must be the point's: else it keeps its value
        raw0 = (_decimal(initial) - offset) / scale
        ramp.raw0 = int(raw0.to_integral_value(rounding=ROUND_HALF_UP))
        encode_point_value(writable, ramp.value(low - ramp.raw0))
        encode_point_value(writable, ramp.value(high - ramp.raw0))
    except (ValueError, ArithmeticError):
        return None
    return ramp


#: a step's writes: (the store's table, its address: value pairs, its (address,
#: and_mask, or_mask) masks of bit fields)
StepWrites = list[tuple[str, list[tuple[int, Any]], list[tuple[int, int, int]]]]


class VaryPlan:
    """The measured points' ramps of one template (``--vary SECONDS``, see the module
    docstring), shared by its simulators with the same initial values: each step's
    registers are computed once (the last step's kept)."""

    def __init__(self, period: float, ramps: list[_Ramp], clock: Any = time.monotonic) -> None:
        self.period = period
        self.ramps = ramps
        self.clock = clock
        self.started = clock()
        #: the last step's writes, one tuple (the simulators of a range and ``--watch``
        #: may ask from two threads)
        self._last: tuple[int, StepWrites] = (-1, [])

    def step_now(self) -> int:
        """The present step: whole periods since the plan was made."""
        return int((self.clock() - self.started) // self.period)

    def writes(self, k: int) -> StepWrites:
        """What step ``k`` stores, by table."""
        step, writes = self._last
        if step == k:
            return writes
        by_table: dict[str, tuple[list[tuple[int, Any]], list[tuple[int, int, int]]]] = {}
        for ramp in self.ramps:
            enc = encode_point_value(ramp.writable, ramp.value(k))
            pairs, masks = by_table.setdefault(STORE_TABLES[ramp.point.table], ([], []))
            keep = 0xFFFF & ~_field_mask(ramp.point)  # the register's bits of other points
            if enc.mask is not None:
                masks.append((ramp.point.address, *enc.mask))
            elif keep and not ramp.point.bit_table:  # a byte of the register
                masks.append((ramp.point.address, keep, int(enc.words[0]) & ~keep))
            else:
                pairs.extend(zip(range(ramp.point.address, ramp.point.end), enc.words, strict=True))
        writes = [(t, pairs, masks) for t, (pairs, masks) in by_table.items()]
        self._last = (k, writes)
        return writes


#: the plans made lately, by (template id, period, initial values) (the template kept)
_PLANS: dict[tuple[int, float, str], tuple[Template, VaryPlan]] = {}


def vary_plan(sim: TemplateSimulator, initial: Mapping[str, Any], period: float) -> VaryPlan:
    """The `VaryPlan` of ``sim``'s template and ``initial`` values (one per template,
    period and values: the simulators of a ``--tcp`` range share it)."""
    key = (id(sim.template), period, repr(sorted(initial.items())))
    got = _PLANS.get(key)
    if got is not None and got[0] is sim.template:
        return got[1]
    if len(_PLANS) >= 8:
        _PLANS.clear()
    writable = [p for p in sim.points if sim.hints[p.name].get("writable")]
    ramps: list[_Ramp] = []
    # of aliases, the one whose initial value was given steps (its value is the registers')
    for p in sorted(sim.points, key=lambda p: p.name not in sim._given):
        if sim.hints[p.name].get("writable") or any(_shared(p, w) for w in writable):
            continue  # a client's to write, or an alias of what a client writes
        if any(_shared(p, r.point) for r in ramps):
            continue  # an alias of a point already varied
        ramp = _ramp(p, sim._writable[p.name], sim.hints[p.name], initial[p.name])
        if ramp is not None:
            ramps.append(ramp)
    plan = VaryPlan(period, ramps)
    _PLANS[key] = (sim.template, plan)
    return plan


def _refuse(address: int, value: object) -> bool:
    raise SlaveException(2, f"address {address} is a gap between points: not writable")


__all__ = ["TemplateSimulator", "VaryPlan", "read_values", "vary_plan"]
