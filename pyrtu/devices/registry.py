"""The registry of device templates: one TOML file per device model.

A template describes a device model as data (docs/TEMPLATES.md)::

    [device]
    vendor = "Eastron"
    model = "SDM630"
    word_order = "ABCD"
    max_registers = 40
    identify = { vendor = "Eastron", product = "SDM630" }

    [[point]]
    name = "voltage_l1"
    table = "input"
    address = 0x0000
    type = "float32"
    unit = "V"

The registry is every template the commands can name: the built-in ones shipped
in ``pyrtu/devices/templates/`` (the drives of the manuals) and the user's, in the
folders of ``PYRTU_TEMPLATE_PATH`` (separated as ``PATH`` is), searched first.  A
template's name is its path inside its folder without ``.toml``
(``meters/sdm630``); a name in two folders is the first folder's.  Adding a device
is adding a file.

This module reads the ``[device]`` table; the ``[[point]]`` tables are the
poller's (`pyrtu.poller.config.template_points` makes them `Point` objects with the
poller's own point parser).  A leaf: it imports nothing of pyrtu.  Errors are
`TemplateError` (a ValueError) naming the file, the line, the table and the key.
"""

from __future__ import annotations

import importlib
import math
import os
import re
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pyrtu.core._text import read_text_file
from pyrtu.core._tomlpos import locate

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: the environment variable naming the user's template folders
TEMPLATE_PATH_ENV = "PYRTU_TEMPLATE_PATH"
#: the built-in templates (package data)
BUILTIN_DIR = Path(__file__).resolve().parent / "templates"
#: the JSON Schema of the format (package data)
SCHEMA_PATH = Path(__file__).resolve().parent / "template.schema.json"

#: ``identify`` keys -> the FC 43 object id they are (Application Protocol 6.21)
IDENTIFY_OBJECTS: Mapping[str, int] = {
    "vendor": 0x00,
    "product": 0x01,
    "revision": 0x02,
    "url": 0x03,
    "product_name": 0x04,
    "model_name": 0x05,
}
#: the per-request limits a ``[device]`` may give (the poller's `Limits`)
LIMIT_KEYS = ("max_registers", "max_bits", "max_adu", "max_gap")
#: the code hooks of ``[device]``: what data cannot say (pyrtu.devices only)
HOOK_KEYS = ("profile", "simulator", "describe")
#: the vendor function sets a ``rules`` key may name (`pyrtu.core.rules`)
RULES = ("bonfiglioli", "cv100")
WORD_ORDERS = ("ABCD", "CDAB", "BADC", "DCBA")
MODES = ("rtu", "ascii")
DEVICE_KEYS = (
    "vendor", "model", "description", "word_order", *LIMIT_KEYS, "response_delay",
    "identify", "probe", "address", "modes", "functions", "interval", "rules", *HOOK_KEYS,
)  # fmt: skip
PROBE_KEYS = ("table", "address", "value")
PROBE_TABLES = ("holding", "input")
#: the keys a template's ``[[point]]`` adds to the poller's: the simulator's initial
#: value, the bounds and writability of a set value, and Home Assistant's hints
#: (``unit`` and ``precision`` too while the poller's points do not carry them)
POINT_HINT_KEYS = (
    "unit", "precision", "writable", "min", "max", "initial",
    "device_class", "state_class", "icon",
)  # fmt: skip
STATE_CLASSES = ("measurement", "total", "total_increasing")


class TemplateError(ValueError):
    """A template that cannot be used (the message names the file, line and key)."""


def _real(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


def _int(v: object, lo: int, hi: int) -> bool:
    return not isinstance(v, bool) and isinstance(v, int) and lo <= v <= hi


def check_hint(key: str, value: object) -> str | None:
    """What is wrong with a template point's ``key`` = ``value`` (None: nothing)."""
    if key in ("unit", "device_class", "icon"):
        ok = isinstance(value, str) and value.strip() != ""
        return None if ok else f"must be a non-empty string, not {value!r}"
    if key == "state_class":
        ok = value in STATE_CLASSES
        return None if ok else f"must be one of {', '.join(STATE_CLASSES)}, not {value!r}"
    if key == "precision":
        return None if _int(value, 0, 15) else f"must be an integer 0..15, not {value!r}"
    if key == "writable":
        return None if isinstance(value, bool) else f"must be true or false, not {value!r}"
    if key in ("min", "max"):
        return None if _real(value) else f"must be a finite number, not {value!r}"
    if key == "initial":
        ok = isinstance(value, bool | str) or _real(value)
        return None if ok else f"must be a number, true/false or a string, not {value!r}"
    return "unknown key"


@dataclass(frozen=True)
class Probe:
    """A register whose value names the model: ``table`` (holding or input) at
    ``address`` reads ``value`` (read with FC 03 or 04)."""

    table: str
    address: int
    value: int


@dataclass(frozen=True)
class Template:
    """One device model: the ``[device]`` table's keys, the raw ``[[point]]`` tables
    (the poller parses them) and where it came from (``source`` in errors, ``text``
    to find lines)."""

    name: str
    source: str
    text: str
    vendor: str
    model: str
    points: tuple[Mapping[str, Any], ...]
    path: Path | None = None
    builtin: bool = False
    description: str = ""
    word_order: str = "ABCD"
    limits: Mapping[str, int] = field(default_factory=dict)
    response_delay: float = 0.0
    identify: Mapping[str, str] = field(default_factory=dict)
    probe: Probe | None = None
    address: int = 1
    modes: tuple[str, ...] = ("rtu",)
    functions: tuple[int, ...] | None = None
    interval: float | None = None
    rules: str | None = None
    hooks: Mapping[str, str] = field(default_factory=dict)

    @property
    def title(self) -> str:
        """``vendor model`` (what a user calls the device)."""
        return f"{self.vendor} {self.model}".strip()

    def fail(
        self, table: str, key: str | None, msg: str, index: int | None = None
    ) -> TemplateError:
        """The error of ``key`` in ``[table]`` (or the ``index``-th ``[[table]]``)."""
        line = locate(self.text, table, key, index)
        where = f"{self.source}:{line}" if line else self.source
        label = table if index is None else f"{table}[{index}]"
        return TemplateError(
            f"{where}: {label}: {key}: {msg}" if key else f"{where}: {label}: {msg}"
        )

    def identification(self) -> dict[int, bytes]:
        """The FC 43 objects the device answers with (``identify``; else its vendor
        and model as VendorName and ProductCode)."""
        objects = dict(self.identify) or {"vendor": self.vendor or "-", "product": self.model}
        return {IDENTIFY_OBJECTS[k]: v.encode() for k, v in objects.items()}

    def matches_identity(self, objects: Mapping[int, str]) -> bool:
        """Whether FC 43 ``objects`` (object id -> text) are this template's
        ``identify`` (every key given; case and surrounding blanks ignored)."""
        if not self.identify:
            return False
        for key, want in self.identify.items():
            got = objects.get(IDENTIFY_OBJECTS[key])
            if got is None or got.strip().casefold() != want.strip().casefold():
                return False
        return True

    def hook(self, key: str) -> Any:
        """The object a code hook names (``module:attribute`` in pyrtu.devices), None
        without it."""
        ref = self.hooks.get(key)
        if ref is None:
            return None
        module, _, attr = ref.partition(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as e:
            raise self.fail("device", key, f"{ref!r} cannot be loaded: {e}") from None


class _Checker:
    def __init__(self, text: str, source: str) -> None:
        self.text = text
        self.source = source

    def fail(
        self, table: str, key: str | None, msg: str, index: int | None = None
    ) -> TemplateError:
        blank = Template("", self.source, self.text, "", "", ())
        return blank.fail(table, key, msg, index)

    def device(self, t: Mapping[str, Any]) -> dict[str, Any]:
        for k in t:
            if k not in DEVICE_KEYS:
                raise self.fail("device", k, f"unknown key (known: {', '.join(DEVICE_KEYS)})")
        out: dict[str, Any] = {"vendor": ""}
        if "model" not in t:
            raise self.fail("device", None, "model: missing")
        for k in ("vendor", "model", "description"):
            if k in t:
                v = t[k]
                if not isinstance(v, str) or (k != "description" and not v.strip()):
                    raise self.fail("device", k, f"must be a non-empty string, not {v!r}")
                out[k] = v
        if "word_order" in t:
            v = t["word_order"]
            order = v.upper() if isinstance(v, str) else v
            if order not in WORD_ORDERS:
                raise self.fail(
                    "device", "word_order", f"must be one of {', '.join(WORD_ORDERS)}, not {v!r}"
                )
            out["word_order"] = order
        limits = {}
        for k, lo, hi in (("max_registers", 1, 125), ("max_bits", 1, 2000), ("max_adu", 6, 256),
                          ("max_gap", 0, 0xFFFF)):  # fmt: skip
            if k in t:
                if not _int(t[k], lo, hi):
                    raise self.fail("device", k, f"must be an integer {lo}..{hi}, not {t[k]!r}")
                limits[k] = t[k]
        out["limits"] = limits
        if "response_delay" in t:
            v = t["response_delay"]
            if not _real(v) or not 0 <= v <= 10:
                raise self.fail("device", "response_delay", f"must be 0..10 seconds, not {v!r}")
            out["response_delay"] = float(v)
        if "interval" in t:
            v = t["interval"]
            if not _real(v) or v <= 0:
                raise self.fail("device", "interval", f"must be a positive number, not {v!r}")
            out["interval"] = float(v)
        if "address" in t:
            if not _int(t["address"], 0, 255):
                raise self.fail(
                    "device", "address", f"must be an integer 0..255, not {t['address']!r}"
                )
            out["address"] = t["address"]
        if "identify" in t:
            out["identify"] = self.identify(t["identify"])
        if "probe" in t:
            out["probe"] = self.probe(t["probe"])
        if "modes" in t:
            v = t["modes"]
            if (
                not isinstance(v, list)
                or not v
                or any(m not in MODES for m in v)
                or len(set(v)) != len(v)
            ):
                raise self.fail(
                    "device", "modes", f"must be a list of {' and '.join(MODES)}, not {v!r}"
                )
            out["modes"] = tuple(v)
        if "functions" in t:
            v = t["functions"]
            if not isinstance(v, list) or not v or not all(_int(f, 1, 127) for f in v):
                raise self.fail(
                    "device", "functions", f"must be a list of function codes 1..127, not {v!r}"
                )
            out["functions"] = tuple(sorted(set(v)))
        if "rules" in t:
            if t["rules"] not in RULES:
                raise self.fail(
                    "device", "rules", f"must be one of {', '.join(RULES)}, not {t['rules']!r}"
                )
            out["rules"] = t["rules"]
        if "identify" in out and 43 not in out.get("functions", (43,)):
            raise self.fail(
                "device", "identify", "needs function 43 in functions (FC 43 answers it)"
            )
        hooks = {}
        for k in HOOK_KEYS:
            if k in t:
                v = t[k]
                if not isinstance(v, str) or not re.fullmatch(r"pyrtu\.devices\.\w+:\w+", v):
                    raise self.fail(
                        "device",
                        k,
                        f'must be "pyrtu.devices.MODULE:NAME" (code of pyrtu), not {v!r}',
                    )
                hooks[k] = v
        out["hooks"] = hooks
        return out

    def identify(self, v: object) -> dict[str, str]:
        if not isinstance(v, Mapping) or not v:
            raise self.fail(
                "device", "identify", f"must be a table of {', '.join(IDENTIFY_OBJECTS)}, not {v!r}"
            )
        for k, s in v.items():
            if k not in IDENTIFY_OBJECTS:
                raise self.fail(
                    "device", "identify", f"{k}: unknown key (known: {', '.join(IDENTIFY_OBJECTS)})"
                )
            if not isinstance(s, str) or not s.strip() or not s.isascii() or len(s) > 200:
                raise self.fail(
                    "device", "identify", f"{k}: must be ASCII text (1..200), not {s!r}"
                )
        return dict(v)

    def probe(self, v: object) -> Probe:
        if not isinstance(v, Mapping):
            raise self.fail(
                "device", "probe", f"must be a table (table, address, value), not {v!r}"
            )
        for k in v:
            if k not in PROBE_KEYS:
                raise self.fail(
                    "device", "probe", f"{k}: unknown key (known: {', '.join(PROBE_KEYS)})"
                )
        table = v.get("table", "holding")
        if table not in PROBE_TABLES:
            raise self.fail("device", "probe", f"table: must be holding or input, not {table!r}")
        for k in ("address", "value"):
            if k not in v:
                raise self.fail("device", "probe", f"{k}: missing")
            if not _int(v[k], 0, 0xFFFF):
                raise self.fail(
                    "device", "probe", f"{k}: must be an integer 0..65535, not {v[k]!r}"
                )
        return Probe(table, v["address"], v["value"])


def _top_level_line(text: str, key: str) -> int | None:
    """The line of a top-level ``key``: its table's header (``[key]``, ``[[key]]``)
    or, before the first header, ``key = ...``."""
    header = re.compile(r"^\s*\[\[?\s*" + re.escape(key) + r"\s*[\].]")
    plain = re.compile(r"^\s*" + re.escape(key) + r"\s*=")
    in_tables = False
    for n, line in enumerate(text.splitlines()):
        if header.match(line) or (not in_tables and plain.match(line)):
            return n + 1
        in_tables = in_tables or line.lstrip().startswith("[")
    return None


def parse_template(
    text: str, source: str = "<template>", name: str = "", path: Path | None = None,
    builtin: bool = False,
) -> Template:  # fmt: skip
    """A template from TOML text (``source`` names it in errors)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TemplateError(f"{source}: {e}") from None
    check = _Checker(text, source)
    for k in doc:
        if k not in ("device", "point"):
            line = _top_level_line(text, k)
            where = f"{source}:{line}" if line else source
            raise TemplateError(f"{where}: unknown top-level key {k!r} (known: device, point)")
    dev = doc.get("device")
    if not isinstance(dev, Mapping):
        raise TemplateError(f"{source}: no [device] table (model at least)")
    keys = check.device(dev)
    points = doc.get("point", [])
    if not isinstance(points, list) or not all(isinstance(p, Mapping) for p in points):
        raise TemplateError(f"{source}: point: must be an array of tables ([[point]])")
    if not points:
        raise TemplateError(f"{source}: no [[point]] table")
    return Template(
        name or keys["model"].lower(), source, text, points=tuple(points), path=path,
        builtin=builtin, **keys,
    )  # fmt: skip


def load_template(path: str | Path, name: str = "", builtin: bool = False) -> Template:
    """A template from a file (`TemplateError` names the file on any problem)."""
    p = Path(path)
    text = read_text_file(p, TemplateError)
    return parse_template(text, str(p), name or p.stem, p, builtin)


def template_dirs(environ: Mapping[str, str] | None = None) -> list[tuple[Path, bool]]:
    """The folders searched, in order: ``PYRTU_TEMPLATE_PATH``'s, then the built-in
    one; each with whether it is the built-in one."""
    env = os.environ if environ is None else environ
    user = [Path(d) for d in env.get(TEMPLATE_PATH_ENV, "").split(os.pathsep) if d]
    return [*((d, False) for d in user), (BUILTIN_DIR, True)]


@dataclass(frozen=True)
class Entry:
    """A template the registry names: its ``name``, file and whether it is built in;
    ``shadows``: the files of the same name in later folders (not used)."""

    name: str
    path: Path
    builtin: bool
    shadows: tuple[Path, ...] = ()

    def load(self) -> Template:
        return load_template(self.path, self.name, self.builtin)


def entries(environ: Mapping[str, str] | None = None) -> dict[str, Entry]:
    """Every template name of the registry -> its `Entry` (sorted by name)."""
    found: dict[str, Entry] = {}
    for folder, builtin in template_dirs(environ):
        if not folder.is_dir():
            continue
        for path in sorted(folder.rglob("*.toml")):
            name = path.relative_to(folder).with_suffix("").as_posix()
            if name in found:
                old = found[name]
                found[name] = Entry(old.name, old.path, old.builtin, (*old.shadows, path))
            else:
                found[name] = Entry(name, path, builtin)
    return dict(sorted(found.items()))


def builtin_names() -> tuple[str, ...]:
    """The names of the built-in templates."""
    return tuple(e.name for e in entries({}).values())


def names(environ: Mapping[str, str] | None = None) -> tuple[str, ...]:
    return tuple(entries(environ))


def is_file_reference(ref: str) -> bool:
    """A ``template =`` naming a file (``*.toml``) rather than a registry name."""
    return ref.endswith(".toml")


def find_template(
    ref: str, base: Path | None = None, environ: Mapping[str, str] | None = None
) -> Template:
    """The template ``ref`` names: a file (``meters/sdm630.toml``, relative to
    ``base``) or a registry name (``cfw701``, ``meters/sdm630``; any case).
    `TemplateError` when there is none."""
    if not isinstance(ref, str) or not ref:
        raise TemplateError(f"must be a template name or a .toml file, not {ref!r}")
    if is_file_reference(ref):
        p = Path(ref).expanduser()
        if not p.is_absolute() and base is not None:
            p = base / p
        return load_template(p)
    known = entries(environ)
    entry = known.get(ref) or known.get(ref.lower())
    if entry is None:
        raise TemplateError(
            f"no template named {ref!r} (templates: {', '.join(known) or 'none'}; "
            f"a file must end in .toml; more folders in {TEMPLATE_PATH_ENV})"
        )
    return entry.load()


def templates(environ: Mapping[str, str] | None = None) -> Iterable[Template]:
    """Every template of the registry, loaded."""
    for entry in entries(environ).values():
        yield entry.load()


__all__ = [
    "BUILTIN_DIR",
    "DEVICE_KEYS",
    "IDENTIFY_OBJECTS",
    "POINT_HINT_KEYS",
    "SCHEMA_PATH",
    "TEMPLATE_PATH_ENV",
    "Entry",
    "Probe",
    "Template",
    "TemplateError",
    "builtin_names",
    "check_hint",
    "entries",
    "find_template",
    "is_file_reference",
    "load_template",
    "locate",
    "names",
    "parse_template",
    "template_dirs",
    "templates",
]
