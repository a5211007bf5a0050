"""The poller's configuration: buses, devices and points, in Python or TOML.

(Not the line: each `Bus` makes its `pyrtu.core.line.LineConfig` once, from its line
keywords, and its master is opened with it; `pyrtu.core.options` is the framer core's
options.)

Minimal TOML (``[[bus]]`` keys are `pyrtu.Master`'s keywords; ``[[point]]`` keys
are `Point`'s fields)::

    [[bus]]
    name = "line1"
    port = "/dev/ttyUSB0"
    baudrate = 19200
    parity = "E"

    [[point]]
    name = "cfw701.status"
    bus = "line1"
    slave = 1
    table = "holding"
    address = 680
    type = "uint16"
    interval = 0.1

Added keys: on a bus, the poller's ``share`` (of bus time an offline slave's
probes may take, default 0.05), ``offline_after`` (failures, default 3),
``backoff``/``max_backoff`` (seconds, default 0.5 and 1) and default device limits
(``max_registers``, ``max_bits``, ``max_adu``, ``max_gap``); ``[[device]]`` tables
(``bus``, ``slave``, the same limits, and ``template`` = a device template
(a ``.toml`` file, relative to the configuration's folder, or a name of the
registry, `pyrtu.devices.registry`; ``profile`` is the same for a registry name)
with ``name``/``interval`` to add its points, named ``name.point``); a
``[defaults]`` table whose keys are defaults of every point (``bus``, ``table``,
``interval``...); a ``[connect]`` table: how network buses connect
(`pyrtu.poller.connect.ConnectLimits`, docs/many-devices.md).

Errors are `ConfigError` (a ValueError) naming the file, the line where it can be
found, the table and key, and what is wrong::

    points.toml:14: point[3] ("cfw701.speed"): address: must be 0..65535, not -1
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, TypeGuard

from pyrtu.core._text import read_text_file
from pyrtu.core._tomlpos import locate
from pyrtu.core.line import LineConfig, split_field_error
from pyrtu.devices.registry import (
    POINT_HINT_KEYS,
    Template,
    TemplateError,
    check_hint,
    find_template,
    is_file_reference,
    names,
)
from pyrtu.drivers._portname import first_duplicate
from pyrtu.drivers.links import check_tls, transport_of

from .connect import ConnectLimits, connect_limits
from .plan import Limits, Wire
from .points import (
    HA_KEYS,
    Point,
    PointError,
    RegisterIndex,
    check_unique,
    encode_point_value,
    overlap_problem,
)
from .schedule import BACKOFF, MAX_BACKOFF

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


class ConfigError(ValueError):
    """A configuration that cannot be used (the message names where and why)."""


#: `pyrtu.Master` keywords a ``[[bus]]`` may carry, with their checks
MASTER_KEYS = ("baudrate", "parity", "stopbits", "bytesize", "timeout", "retries", "t15", "t35",
               "timing", "mode", "echo", "broadcast_delay", "max_adu", "strict")  # fmt: skip
POLLER_KEYS = ("share", "offline_after", "backoff", "max_backoff")
#: an ``mbaps://`` bus's TLS files (PEM; relative to the configuration file): its
#: certificate, its key and the CA the server's certificate must be signed by
TLS_KEYS = ("tls_cert", "tls_key", "tls_ca")
LIMIT_KEYS = ("max_registers", "max_bits", "max_adu", "max_gap")
POINT_KEYS = tuple(f.name for f in fields(Point) if f.init)


def _real(v: object) -> TypeGuard[float]:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


#: the `LineConfig` fields among them (checked by `LineConfig` itself)
LINE_KEYS = ("baudrate", "parity", "stopbits", "bytesize", "mode", "timing", "t15", "t35",
             "max_adu", "strict")  # fmt: skip


def _check_master(key: str, v: object) -> str | None:
    """What is wrong with a Master-only keyword ``key`` = ``v`` (None: nothing)."""
    if key == "timeout":
        return None if _real(v) and v > 0 else f"must be a positive number of seconds, not {v!r}"
    if key == "broadcast_delay":
        ok = _real(v) and v >= 0
        return None if ok else f"must be a non-negative number of seconds, not {v!r}"
    if key == "retries":
        ok = not isinstance(v, bool) and isinstance(v, int) and v >= 0
        return None if ok else f"must be a non-negative integer, not {v!r}"
    if key == "echo":
        return None if isinstance(v, bool) else f"must be true or false, not {v!r}"
    return "unknown key"


def make_line(master: Mapping[str, Any]) -> LineConfig:
    """The `LineConfig` of a bus's Master keywords; ValueError ``"key: what"``."""
    kw = {k: master[k] for k in LINE_KEYS if k in master}
    try:
        return LineConfig(**kw)
    except (ValueError, TypeError) as e:  # LineConfig's own words after "key: "
        key, detail = split_field_error(e, LINE_KEYS)
        raise ValueError(f"{key}: {detail}" if key else detail) from None


@dataclass(frozen=True)
class Bus:
    """One serial line: ``port`` and `pyrtu.Master` keywords (``master``), the
    poller's slave-health settings and the default limits of its devices."""

    name: str
    port: Any
    master: Mapping[str, Any] = field(default_factory=dict)
    share: float = 0.05
    offline_after: int = 3
    backoff: float = BACKOFF
    max_backoff: float = MAX_BACKOFF
    limits: Limits = field(default_factory=Limits)
    #: an ``mbaps://`` bus's client context (`pyrtu.security.tls.client_context`;
    #: required there, refused elsewhere), passed to the master as ``tls``
    tls: Any = field(default=None, compare=False)
    #: the files it was made of (``tls_cert``, ``tls_key``, ``tls_ca``), when a
    #: configuration file named them: a bus is the same bus with the same files
    tls_files: tuple[str, str, str] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name: must be a non-empty string, not {self.name!r}")
        if self.port is None or (isinstance(self.port, str) and not self.port):
            raise ValueError("port: missing")
        for k, v in self.master.items():
            wrong = None if k in LINE_KEYS else _check_master(k, v)
            if wrong:
                raise ValueError(f"{k}: {wrong}")
        line = dict(self.master)
        try:
            transport = transport_of(self.port)
            transport.check_port(self.port)  # (a URL without a host, a port too high...)
        except ValueError as exc:  # a URL scheme no one opens, a URL it cannot open
            raise ValueError(f"port: {str(exc).removeprefix(f'{self.port}: ')}") from None
        if transport.t35 is not None:
            line.setdefault("t35", transport.t35)  # as the master: a socket has no wire timing
        check_tls(transport, self.tls)
        object.__setattr__(self, "_line", make_line(line))
        if not (_real(self.share) and 0 < self.share <= 1):
            raise ValueError(f"share: must be a fraction in (0, 1], not {self.share!r}")
        oa = self.offline_after
        if isinstance(oa, bool) or not isinstance(oa, int) or oa < 1:
            raise ValueError(f"offline_after: must be a positive integer, not {oa!r}")
        if not (_real(self.backoff) and self.backoff > 0):
            raise ValueError(f"backoff: must be a positive number of seconds, not {self.backoff!r}")
        if not (_real(self.max_backoff) and self.max_backoff >= self.backoff):
            raise ValueError(f"max_backoff: must be at least backoff, not {self.max_backoff!r}")

    @property
    def line(self) -> LineConfig:
        """The bus's line configuration (from the Master keywords)."""
        line: LineConfig = self.__dict__["_line"]
        return line

    @property
    def master_options(self) -> dict[str, Any]:
        """The bus's Master keywords other than the line's (the master is opened with
        ``line=bus.line`` and these: the line is checked once, here)."""
        options = {k: v for k, v in self.master.items() if k not in LINE_KEYS}
        if self.tls is not None:
            options["tls"] = self.tls
        return options

    def wire(self) -> Wire:
        """The bus's wire model from its line (an estimated turnaround of t3.5 until
        the slaves' are measured); an MBAP bus's (``tcp://``, ``mbaps://``, ``udp://``:
        `pyrtu.drivers.links.Transport.mbap`) is `Wire.tcp` (its round trip, no
        character time)."""
        if transport_of(self.port).mbap:
            return Wire.tcp()
        line = self.line
        return Wire(
            line.char_time,
            line.frame_gap,
            turnaround=max(line.t35_time, line.char_time),
            ascii=line.mode == "ascii",
        )


def unit_problem(bus: Bus, slave: object) -> str | None:
    """What is wrong with ``slave`` on ``bus`` (None: nothing): an MBAP bus
    (``tcp://``, ``mbaps://``, ``udp://``: `pyrtu.drivers.links.Transport.mbap`) takes
    unit ids 0..255 (0: the TCP device itself, 255 and 248..254: what is behind it,
    as `pyrtu.Master` on TCP does), a serial bus (and ``rtu+tcp://``) 1..247 (0 is
    the broadcast: no answer to poll)."""
    transport = transport_of(bus.port)
    tcp = transport.mbap
    lo, hi = (0, 255) if tcp else (1, 247)
    if isinstance(slave, bool) or not isinstance(slave, int) or not lo <= slave <= hi:
        why = (
            f" on a {transport.what} bus"
            if tcp
            else f" on serial bus {bus.name!r} (0..255 on tcp://)"
        )
        return f"must be an integer {lo}..{hi}{why}, not {slave!r}"
    return None


@dataclass(frozen=True)
class Device:
    """Limits of one slave on a bus (None: the bus's); with a ``template``, its
    ``name`` (the prefix of its points' names) and its points' template keys the
    points do not carry (``hints``: point name -> unit, writable, min, max...)."""

    bus: str
    slave: int
    limits: Limits = field(default_factory=Limits)
    name: str = ""
    template: Template | None = None
    hints: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)


@dataclass(frozen=True)
class PollerConfig:
    """Buses, device limits and points; `check` makes sure they fit together."""

    buses: tuple[Bus, ...]
    points: tuple[Point, ...]
    devices: tuple[Device, ...] = ()
    source: str = "<config>"
    connect: ConnectLimits = field(default_factory=ConnectLimits)

    def bus(self, name: str) -> Bus:
        by_name: dict[str, Bus] | None = self.__dict__.get("_by_name")
        if by_name is None:  # (made once: a thousand buses are looked up by name)
            by_name = {b.name: b for b in reversed(self.buses)}  # the first of a name
            object.__setattr__(self, "_by_name", by_name)
        try:
            return by_name[name]
        except KeyError:
            raise KeyError(name) from None

    def limits(self, bus: str) -> dict[int, Limits]:
        """Per-slave limits on ``bus`` (a device's keys over the bus's)."""
        base = self.bus(bus).limits
        out: dict[int, Limits] = {}
        for d in self.devices:
            if d.bus == bus:
                merged = {k: getattr(base, k) for k in LIMIT_KEYS}
                merged.update({k: v for k in LIMIT_KEYS if (v := getattr(d.limits, k)) is not None})
                out[d.slave] = Limits(**merged)
        return out

    def check(self) -> None:
        """ConfigError when points name unknown buses, names repeat, or a point does
        not fit its device's maximum per request."""
        names = [b.name for b in self.buses]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise ConfigError(f"{self.source}: bus {dup!r} is declared twice")
        twice = first_duplicate(b.port for b in self.buses)
        if twice is not None:
            a, b = self.buses[twice[0]], self.buses[twice[1]]
            raise ConfigError(
                f"{self.source}: bus {b.name!r}: port: {b.port!r} is the port of bus"
                f" {a.name!r} already: one port is one bus (give each bus its own port)"
            )
        if not self.points:
            raise ConfigError(f"{self.source}: no points to poll")
        try:
            check_unique(self.points)
        except PointError as e:
            raise ConfigError(f"{self.source}: point: {e}") from None
        known, per_bus = set(names), {}
        for i, p in enumerate(self.points):
            if p.bus not in known:
                raise ConfigError(
                    f'{self.source}: point[{i}] ("{p.name}"): bus: no bus named {p.bus!r}'
                    f" (buses: {', '.join(names) or 'none'})"
                )
            wrong = unit_problem(self.bus(p.bus), p.slave)
            if wrong:
                raise ConfigError(f'{self.source}: point[{i}] ("{p.name}"): slave: {wrong}')
            if p.bus not in per_bus:
                per_bus[p.bus] = self.limits(p.bus)
            lim = per_bus[p.bus].get(p.slave, self.bus(p.bus).limits)
            most = lim.per_request(p.table)
            if p.size > most:
                raise ConfigError(
                    f'{self.source}: point[{i}] ("{p.name}"): takes {p.size} registers, '
                    f"more than slave {p.slave} reads per request ({most})"
                )
        placed: dict[tuple[str, int, str], RegisterIndex] = {}
        for i, p in enumerate(self.points):
            mine = placed.setdefault((p.bus, p.slave, p.table), RegisterIndex())
            for _, q in mine.overlapping(p):
                problem = overlap_problem(q, p)
                if problem:
                    raise ConfigError(f'{self.source}: point[{i}] ("{p.name}"): address: {problem}')
            mine.add(i, p)


# ---------------------------------------------------------------------- TOML


def _locate(text: str, array: str, index: int, key: str | None) -> int | None:
    """The line (1-based) of ``key`` in the ``index``-th ``[[array]]`` table of
    ``text`` (or of the table header), None when it cannot be found."""
    return locate(text, array, key, index)


class _Loader:
    """``point_keys``/``default_keys``: the keys a caller (the bridge) takes out of
    ``[[point]]``/``[defaults]`` tables before loading, named with the poller's
    own when a key is unknown."""

    def __init__(
        self,
        text: str,
        source: str,
        point_keys: Sequence[str] = (),
        default_keys: Sequence[str] = (),
        base: Path | None = None,
    ) -> None:
        self.text = text
        self.source = source
        #: the folder a ``template = "x.toml"`` is relative to (None: the working one)
        self.base = base
        self._buses: dict[str, Bus] = {}
        self.point_keys = (*POINT_KEYS, *point_keys)
        self.default_keys = (*(k for k in POINT_KEYS if k not in ("name", "address")),
                             *default_keys)  # fmt: skip

    def fail(
        self, array: str, index: int | None, label: str, key: str | None, msg: str
    ) -> ConfigError:
        line = None
        if index is not None:
            line = _locate(self.text, array, index, key)
        elif array:
            m = re.search(r"^\s*\[\s*" + re.escape(array) + r"\s*\]", self.text, re.M)
            line = self.text.count("\n", 0, m.start()) + 1 if m else None
        where = f"{self.source}:{line}" if line else self.source
        what = f"{label}: {key}: {msg}" if key else f"{label}: {msg}"
        return ConfigError(f"{where}: {what}")

    def tables(self, doc: Mapping[str, Any], name: str) -> list[Mapping[str, Any]]:
        got = doc.get(name, [])
        if isinstance(got, Mapping):
            got = [got]
        if not isinstance(got, list) or not all(isinstance(t, Mapping) for t in got):
            raise self.fail("", None, name, None, f"must be an array of tables ([[{name}]])")
        return got

    def load(self, doc: Mapping[str, Any]) -> PollerConfig:
        unknown = sorted(set(doc) - {"bus", "point", "device", "defaults", "connect"})
        if unknown:
            raise ConfigError(
                f"{self.source}: unknown top-level key {unknown[0]!r} "
                "(known: bus, point, device, defaults, connect)"
            )
        defaults = doc.get("defaults", {})
        if not isinstance(defaults, Mapping):
            raise ConfigError(f"{self.source}: defaults: must be a table ([defaults])")
        for k in defaults:
            if k not in POINT_KEYS or k in ("name", "address"):
                raise self.fail(
                    "defaults",
                    None,
                    "defaults",
                    k,
                    f"unknown key (known: {', '.join(self.default_keys)})",
                )
        buses = [self.bus(i, t) for i, t in enumerate(self.tables(doc, "bus"))]
        if not buses:
            raise ConfigError(f"{self.source}: no [[bus]] table")
        names = [b.name for b in buses]
        dup = first_duplicate(b.port for b in buses)
        if dup is not None and len(set(names)) == len(names):  # a name twice: said first
            first, again = buses[dup[0]], buses[dup[1]]
            raise self.fail(
                "bus", dup[1], f'bus[{dup[1]}] ("{again.name}")', "port",
                f"{again.port!r} is the port of bus[{dup[0]}] (\"{first.name}\") already:"
                " one port is one bus (give each bus its own port)",
            )  # fmt: skip
        devices: list[Device] = []
        points: list[Point] = []
        for i, t in enumerate(self.tables(doc, "device")):
            dev, extra = self.device(i, t, buses)
            devices.append(dev)
            points += extra
        for i, t in enumerate(self.tables(doc, "point")):
            points.append(self.point(i, t, defaults, buses))
        connect = self.connect(doc.get("connect", {}))
        cfg = PollerConfig(tuple(buses), tuple(points), tuple(devices), self.source, connect)
        self.check(cfg, len(points) - len(self.tables(doc, "point")))
        return cfg

    def connect(self, table: object) -> ConnectLimits:
        """The ``[connect]`` table (ConfigError naming its line and key)."""
        if not isinstance(table, Mapping):
            raise ConfigError(f"{self.source}: connect: must be a table ([connect])")
        try:
            return connect_limits(table)
        except (ValueError, TypeError) as e:
            key, _, msg = str(e).partition(": ")
            lines = self.text.splitlines()
            header = re.compile(r"^[ \t]*\[[ \t]*connect[ \t]*\]")
            want = re.compile(r"^[ \t]*" + re.escape(key) + r"[ \t]*=")
            start = next((n for n, text in enumerate(lines) if header.match(text)), None)
            line = start
            for n in range(len(lines) if start is None else start + 1, len(lines)):
                if lines[n].lstrip().startswith("["):
                    break
                if want.match(lines[n]):
                    line = n
                    break
            where = self.source if line is None else f"{self.source}:{line + 1}"
            raise ConfigError(f"{where}: connect: {key}: {msg}") from None

    def check(self, cfg: PollerConfig, n_profile: int) -> None:
        try:
            cfg.check()
        except ConfigError as e:
            m = re.match(re.escape(self.source) + r": point\[(\d+)\] (.*)", str(e))
            if m and int(m.group(1)) >= n_profile:
                idx = int(m.group(1)) - n_profile
                key = next((k for k in ("bus", "slave", "address") if f": {k}:" in str(e)), None)
                line = _locate(self.text, "point", idx, key)
                raise ConfigError(f"{self.source}:{line}: point[{idx}] {m.group(2)}") from None
            raise

    def check_keys(
        self,
        array: str,
        i: int,
        label: str,
        t: Mapping[str, Any],
        known: Sequence[str],
        required: Sequence[str],
        present: Mapping[str, Any],
    ) -> None:
        """Fails at the first key of ``t`` not in ``known``, then at the first of
        ``required`` not in ``present`` (``t``, or ``t`` with the defaults)."""
        for k in t:
            if k not in known:
                raise self.fail(array, i, label, k, f"unknown key (known: {', '.join(known)})")
        for k in required:
            if k not in present:
                raise self.fail(array, i, label, None, f"{k}: missing")

    def bus(self, i: int, t: Mapping[str, Any]) -> Bus:
        label = f"bus[{i}]" + (f' ("{t["name"]}")' if isinstance(t.get("name"), str) else "")
        known = ("name", "port", *MASTER_KEYS, *POLLER_KEYS, *LIMIT_KEYS, *TLS_KEYS)
        self.check_keys("bus", i, label, t, known, ("name", "port"), t)
        master = {k: t[k] for k in MASTER_KEYS if k in t}
        poller = {k: t[k] for k in POLLER_KEYS if k in t}
        limits = self.limits("bus", i, label, t)
        if not isinstance(t["port"], str):
            raise self.fail("bus", i, label, "port", f"must be a string, not {t['port']!r}")
        tls, files = self.bus_tls(i, label, t)
        try:
            bus = Bus(t["name"], t["port"], master, limits=limits, tls=tls, tls_files=files,
                      **poller)  # fmt: skip
        except ValueError as e:
            key, _, msg = str(e).partition(": ")
            raise self.fail("bus", i, label, key if key in known else None, msg or str(e)) from None
        return bus

    def bus_tls(
        self, i: int, label: str, t: Mapping[str, Any]
    ) -> tuple[Any, tuple[str, str, str] | None]:
        """An ``mbaps://`` bus's client context from its ``tls_*`` files (relative to
        the configuration file), and the files; (None, None) for another port.
        ConfigError at the key: one missing, given for another port, a file that
        does not exist or does not hold what it should."""
        given = [k for k in TLS_KEYS if k in t]
        try:
            mbaps = transport_of(t["port"]).tls
        except ValueError:  # an unknown scheme: said by Bus, at the port
            mbaps = False
        if not mbaps:
            if given:
                raise self.fail(
                    "bus", i, label, given[0],
                    f"only an mbaps:// port takes TLS files, not {t['port']!r}",
                )  # fmt: skip
            return None, None
        missing = [k for k in TLS_KEYS if k not in t]
        if missing:
            raise self.fail(
                "bus", i, label, None,
                f"{missing[0]}: missing (an mbaps:// port needs {', '.join(TLS_KEYS)}:"
                " its certificate, its key and the CA of the server's certificate)",
            )  # fmt: skip
        paths: list[str] = []
        for k in TLS_KEYS:
            value = t[k]
            if not isinstance(value, str) or not value:
                raise self.fail("bus", i, label, k, f"must be a file name, not {value!r}")
            paths.append(str(self.base / value) if self.base is not None else value)
        from pyrtu.security.tls import TlsSetupError, client_context

        cert, key, ca = paths
        try:
            context = client_context(cert, key, ca)
        except TlsSetupError as exc:
            k = f"tls_{exc.option}" if f"tls_{exc.option}" in TLS_KEYS else "tls_cert"
            named = dict(zip(TLS_KEYS, paths, strict=True))
            detail = str(exc).replace("--tls-cert", "tls_cert").replace("--tls-key", "tls_key")
            detail = detail.replace("--tls-ca", "tls_ca")
            detail = detail.removeprefix(f"{k} {named[k]}: ")
            raise self.fail("bus", i, label, k, f"{named[k]}: {detail}") from None
        return context, (cert, key, ca)

    def limits(self, array: str, i: int, label: str, t: Mapping[str, Any]) -> Limits:
        try:
            return Limits(**{k: t[k] for k in LIMIT_KEYS if k in t})
        except ValueError as e:
            key, _, msg = str(e).partition(": ")
            raise self.fail(array, i, label, key, msg) from None

    def device(
        self, i: int, t: Mapping[str, Any], buses: Sequence[Bus]
    ) -> tuple[Device, list[Point]]:
        label = f"device[{i}]"
        known = ("bus", "slave", "template", "profile", "name", "interval", *LIMIT_KEYS)
        self.check_keys("device", i, label, t, known, ("bus", "slave"), t)
        if t["bus"] not in [b.name for b in buses]:
            raise self.fail("device", i, label, "bus", f"no bus named {t['bus']!r}")
        s = t["slave"]
        bus = next(b for b in buses if b.name == t["bus"])
        wrong = unit_problem(bus, s)
        if wrong:
            raise self.fail("device", i, label, "slave", wrong)
        limits = self.limits("device", i, label, t)
        if "template" in t and "profile" in t:
            raise self.fail("device", i, label, "profile", "give template or profile, not both")
        key = "template" if "template" in t else "profile"
        if key not in t:
            if "name" in t or "interval" in t:
                raise self.fail("device", i, label, "name" if "name" in t else "interval",
                                "applies only with template")  # fmt: skip
            return Device(t["bus"], s, limits), []
        ref = t[key]
        try:
            if key == "profile" and (not isinstance(ref, str) or is_file_reference(ref)):
                raise TemplateError(f"must be one of {', '.join(names())}, not {ref!r}")
            template = find_template(ref, self.base)
        except TemplateError as e:
            if key == "profile" and str(e).startswith("no template named"):
                known_names = ", ".join(names())
                msg = f"must be one of {known_names}, not {ref!r}"
                raise self.fail("device", i, label, key, msg) from None
            raise self.fail("device", i, label, key, str(e)) from None
        name = t.get("name", f"{template.name.rsplit('/', 1)[-1]}{s}")
        if not isinstance(name, str) or not name:
            raise self.fail("device", i, label, "name", f"must be a non-empty string, not {name!r}")
        interval = t.get("interval")
        if interval is not None and (not _real(interval) or interval <= 0):
            raise self.fail("device", i, label, "interval",
                            f"must be a positive number of seconds, not {interval!r}")  # fmt: skip
        points, hints = template_points(template, name, t["bus"], s, interval)
        merged = {**template.limits, **{k: t[k] for k in LIMIT_KEYS if k in t}}
        return Device(t["bus"], s, Limits(**merged), name, template, hints), points

    def point(
        self, i: int, t: Mapping[str, Any], defaults: Mapping[str, Any], buses: Sequence[Bus] = ()
    ) -> Point:
        name = t.get("name")
        label = f"point[{i}]" + (f' ("{name}")' if isinstance(name, str) else "")
        merged = {**defaults, **t}
        required = ("name", "bus", "slave", "table", "address")
        self.check_keys("point", i, label, t, self.point_keys, required, merged)
        for k in ("unit", *HA_KEYS):  # given, a text says something
            if isinstance(t.get(k), str) and not t[k].strip():
                raise self.fail("point", i, label, k, f"must be a non-empty string, not {t[k]!r}")
        if len(self._buses) != len(buses):  # (a thousand buses: by name, not searched)
            self._buses = {b.name: b for b in reversed(buses)}
        bus = self._buses.get(merged["bus"]) if isinstance(merged["bus"], str) else None
        wrong = None if bus is None else unit_problem(bus, merged["slave"])
        if wrong:
            where = "point" if "slave" in t else "defaults"
            raise self.fail(where, i if "slave" in t else None, label, "slave", wrong)
        try:
            return Point(**merged)
        except PointError as e:
            key = e.field if e.field in t else None
            if key is None and e.field in defaults:
                raise self.fail(
                    "defaults", None, label, e.field, e.detail + " (from [defaults])"
                ) from None
            raise (
                self.fail("point", i, label, e.field, e.detail)
                if key is None
                else self.fail("point", i, label, key, e.detail)
            ) from None


def parse_config(text: str, source: str = "<config>", base: Path | None = None) -> PollerConfig:
    """A configuration from TOML text (``source`` names it in errors; ``base``: the
    folder a template file is relative to, default the working one)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: {e}") from None
    return _Loader(text, source, base=base).load(doc)


def read_config_text(path: str | Path) -> str:
    """The text of a configuration file; `ConfigError` names the file when it is
    missing, unreadable or not UTF-8 (the poller's and the bridge's loaders)."""
    return read_text_file(path, ConfigError)


def load_config(path: str | Path) -> PollerConfig:
    """A configuration from a TOML file; `ConfigError` names the file on any problem
    (missing, unreadable, not UTF-8, bad TOML, bad values)."""
    p = Path(path)
    return parse_config(read_config_text(p), p.name if p.name else str(p), p.resolve().parent)


#: a template point's keys the poller's `Point` does not take (kept as hints)
HINT_KEYS = tuple(k for k in POINT_HINT_KEYS if k not in POINT_KEYS)
#: the types whose registers take the template's ``word_order``
_WORD_TYPES = frozenset({"int32", "uint32", "float32", "int64", "uint64", "float64"})


def template_points(
    template: Template,
    prefix: str = "",
    bus: str = "template",
    slave: int = 1,
    interval: float | None = None,
) -> tuple[list[Point], dict[str, dict[str, Any]]]:
    """The points of ``template`` on ``bus`` at ``slave``, named ``prefix.name``
    (``prefix`` empty: the template's names), read every ``interval`` seconds where
    a point gives none (None: the template's ``interval``, else 1 s), and each
    point's keys that `Point` does not take (unit, writable, min, max, initial, Home
    Assistant hints).  Each ``[[point]]`` goes through the poller's own point parser;
    `ConfigError` names the template's file, line, point and key."""
    loader = _Loader(template.text, template.source, point_keys=HINT_KEYS)
    defaults: dict[str, Any] = {"bus": bus, "slave": slave}
    every = interval if interval is not None else template.interval
    if every is not None:
        defaults["interval"] = every
    points: list[Point] = []
    placed: dict[str, RegisterIndex] = {}  # by table
    hints: dict[str, dict[str, Any]] = {}
    for i, raw in enumerate(template.points):
        name = raw.get("name")
        label = f"point[{i}]" + (f' ("{name}")' if isinstance(name, str) else "")
        for k in ("bus", "slave"):
            if k in raw:
                msg = "a template's points are on the [[device]]'s bus and slave"
                raise loader.fail("point", i, label, k, msg)
        own = {k: raw[k] for k in HINT_KEYS if k in raw}
        for k, v in own.items():
            wrong = check_hint(k, v)
            if wrong:
                raise loader.fail("point", i, label, k, wrong)
        table = {k: v for k, v in raw.items() if k not in HINT_KEYS}
        own_defaults = dict(defaults)
        if "order" not in table and table.get("type") in _WORD_TYPES:
            own_defaults["order"] = template.word_order
        point = loader.point(i, table, own_defaults)
        for k in POINT_HINT_KEYS:  # the hints a point carries itself, in one place
            carried = getattr(point, k, None)
            if k not in own and not (carried is None or carried is False or carried == ""):
                own[k] = carried
        _check_hints(loader, i, label, point, own)
        mine = placed.setdefault(point.table, RegisterIndex())
        _check_overlap(loader, i, label, point, mine)
        mine.add(i, point)
        if prefix:
            point = replace(point, name=f"{prefix}.{point.name}")
        points.append(point)
        hints[point.name] = own
    try:
        check_unique(points)
    except PointError as e:
        raise ConfigError(f"{template.source}: point: {e}") from None
    return points, hints


def _check_hints(loader: _Loader, i: int, label: str, point: Point, own: Mapping[str, Any]) -> None:
    """ConfigError when the template keys do not fit the point."""
    read_only = point.table not in ("holding", "coils")
    if own.get("writable") and read_only:
        raise loader.fail("point", i, label, "writable", f"the {point.table} table is read only")
    for k in ("min", "max"):
        if k in own and point.type in ("bool", "string"):
            raise loader.fail("point", i, label, k, f"a {point.type} point has no range")
    if "min" in own and "max" in own and own["min"] > own["max"]:
        raise loader.fail(
            "point", i, label, "max", f"must be at least min ({own['min']}), not {own['max']!r}"
        )
    if "initial" in own:
        value = own["initial"]
        try:  # what the registers would hold (as if the table were writable)
            as_written = replace(point, table="coils" if point.bit_table else "holding")
            encode_point_value(as_written, value)
        except ValueError as e:
            msg = str(e).removeprefix(f"point {point.name!r}: ")
            raise loader.fail("point", i, label, "initial", msg) from None
        low, high = own.get("min"), own.get("max")
        if (
            isinstance(value, int | float)
            and not isinstance(value, bool)
            and ((low is not None and value < low) or (high is not None and value > high))
        ):
            raise loader.fail(
                "point", i, label, "initial", f"{value!r} is outside min..max ({low}..{high})"
            )


def _check_overlap(
    loader: _Loader, i: int, label: str, point: Point, earlier: RegisterIndex
) -> None:
    """ConfigError when ``point`` shares addresses with an earlier point of its table
    (``earlier``) of another type or width (the same registers read as the same type,
    an alias, are fine; so are bit fields of one register)."""
    for j, other in earlier.overlapping(point):
        same = (other.address, other.size, other.type) == (point.address, point.size, point.type)
        fields = getattr(point, "bit", None) is not None or getattr(point, "bits", None) not in (
            None,
            (),
        )
        if same or (fields and other.size == point.size == 1):
            continue
        raise loader.fail("point", i, label, "address",
                          f"{point.table} {point.address}..{point.end - 1} ({point.type}) overlaps "
                          f'point[{j}] ("{other.name}") at {other.address}..{other.end - 1} '
                          f"({other.type})")  # fmt: skip


def make_config(
    buses: Iterable[Bus], points: Iterable[Point], devices: Iterable[Device] = ()
) -> PollerConfig:
    """A checked configuration from Python objects (ConfigError on a mismatch)."""
    cfg = PollerConfig(tuple(buses), tuple(points), tuple(devices), "<python>")
    cfg.check()
    return cfg


__all__ = [
    "LIMIT_KEYS",
    "MASTER_KEYS",
    "Bus",
    "ConfigError",
    "Device",
    "PollerConfig",
    "load_config",
    "make_config",
    "parse_config",
    "template_points",
]
