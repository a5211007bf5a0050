"""``pyrtu template list | show NAME | check FILE...``: the registry of device templates.

A device template is one TOML file per device model: its ``[device]`` table
(vendor, model, limits, identity) and its ``[[point]]`` tables (docs/TEMPLATES.md).
The registry is the built-in templates (the drives of the manuals) and the
templates in the folders of ``PYRTU_TEMPLATE_PATH`` (searched first; a template's
name is its path in its folder without ``.toml``, e.g. ``meters/sdm630``).

``list`` names every template of the registry; ``show NAME`` (a name or a
``.toml`` file) prints its device keys and points; ``check FILE...`` loads each
file as the poller, the bridge and the simulator do and says what is wrong:
``file:line: point[2] ("power"): type: must be one of ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import functools
import sys
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import EXIT_OK, EXIT_USAGE, add_json_option, emit

if TYPE_CHECKING:
    from pyrtu.devices.registry import Template
    from pyrtu.drivers.master import Master
    from pyrtu.poller.points import Point


def template_name(text: str) -> str:
    """argparse type of ``--profile NAME``: a template of the registry, checked when
    the command line is read, or a ``.toml`` file (read when the command runs,
    before a byte is sent: relative to the working directory then)."""
    from pyrtu.devices.registry import TemplateError, find_template, is_file_reference

    if is_file_reference(text):
        return text
    try:
        find_template(text)
    except TemplateError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def add_profile_option(p: argparse.ArgumentParser, help: str) -> None:
    """``--profile NAME`` (`template_name`), shared by the commands that can work
    through a device template (read, poll, info, sniff)."""
    p.add_argument("--profile", type=template_name, metavar="NAME", help=help)


@functools.lru_cache(maxsize=16)
def _loaded(ref: str) -> tuple[Template, list[Point], dict[str, dict[str, Any]]]:
    from pyrtu.devices.registry import find_template
    from pyrtu.poller.config import template_points

    template = find_template(ref)
    return (template, *template_points(template))


def load(ref: str) -> Template:
    """The template ``ref`` names (a registry name or a ``.toml`` file), its points
    checked (ValueError naming file, line and key); read once per command."""
    return _loaded(ref)[0]


def points_of(template: Template) -> tuple[list[Point], dict[str, dict[str, Any]]]:
    """The template's points (named as in the template) and their hints."""
    from pyrtu.poller.config import template_points

    return template_points(template)


def identify_device(
    master: Master,
    slave: int,
    templates: list[Template],
    objects: dict[int, str] | None = None,
) -> tuple[Template | None, str, dict[int, str]]:
    """Which of ``templates`` the device at ``slave`` is: (template, how, FC 43
    objects).  First its FC 43 basic identification (``objects`` when already read)
    against each template's ``identify``; then the ``probe`` register of each
    template the device's FC 43 answer cannot judge (it has no ``identify``, or
    the device none).
    ``how``: "identity", "probe", or why nothing matched."""
    from pyrtu.pdu.errors import ModbusError

    why = "no template matches"
    if objects is None:
        try:
            raw = master.read_device_identification(slave)
            objects = {k: v.decode("ascii", "replace") for k, v in raw.items()}
        except ModbusError as exc:
            objects = {}
            why = f"no template matches (no FC 43 identification: {exc})"
    for t in templates:
        if objects and t.matches_identity(objects):
            return t, "identity", objects
    for t in templates:
        probe = t.probe
        if probe is None or (t.identify and objects):
            continue  # a device that names itself is judged by its name
        read = (
            master.read_holding_registers
            if probe.table == "holding"
            else master.read_input_registers
        )
        try:
            value = read(slave, probe.address, 1)[0]
        except ModbusError:
            continue
        if value == probe.value:
            return t, "probe", objects
    return None, why, objects


def register_notes(
    ref: str, address: int, registers: list[int], table: str | None = None
) -> dict[int, str]:
    """Registers read from ``address`` on in the terms of template ``ref``: its
    ``describe`` hook's (a drive's manual), else the name and value of each of its
    points the registers hold whole (``table``: holding or input; None: either)."""
    template, points, hints = _loaded(ref)
    describe = template.hook("describe")
    notes: dict[int, str] = {}
    if describe is not None:
        for i, value in enumerate(registers):
            note = describe(address + i, value)
            if note:
                notes[address + i] = note
        return notes
    for p in points:
        if p.bit_table or (table is not None and p.table != table):
            continue
        if p.address < address or p.end > address + len(registers):
            continue
        decoded = p.decode(registers, address)
        unit = hints.get(p.name, {}).get("unit") or getattr(p, "unit", None)
        said = f"{p.name} = {decoded}" + (f" {unit}" if unit else "")
        notes[p.address] = f"{notes[p.address]}; {said}" if p.address in notes else said
    return notes


def _summary(template: Template) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "name": template.name,
        "vendor": template.vendor,
        "model": template.model,
        "description": template.description,
        "file": str(template.path) if template.path is not None else template.source,
        "builtin": template.builtin,
        "points": len(template.points),
    }
    return doc


def _configure(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = sub.add_parser("list", help="every template of the registry")
    add_json_option(ls, "one JSON document: the templates")
    show = sub.add_parser("show", help="a template's device keys and points")
    show.add_argument("name", metavar="NAME", help="a template name or a .toml file")
    add_json_option(show, "one JSON document: the template")
    check = sub.add_parser("check", help="load template files and say what is wrong")
    check.add_argument("files", nargs="+", metavar="FILE", help="template files (.toml)")
    add_json_option(check, "one JSON document: each file's result")


def _run(args: argparse.Namespace) -> int:
    if args.action == "list":
        return _list(args)
    if args.action == "show":
        return _show(args)
    return _check(args)


def _list(args: argparse.Namespace) -> int:
    from pyrtu.devices.registry import TemplateError, entries, template_dirs

    rows: list[dict[str, Any]] = []
    for entry in entries().values():
        try:
            rows.append(_summary(entry.load()))
        except TemplateError as e:
            rows.append({"name": entry.name, "file": str(entry.path), "builtin": entry.builtin,
                         "error": str(e)})  # fmt: skip
    if args.json:
        emit({"ok": True, "folders": [str(d) for d, _ in template_dirs()], "templates": rows})
        return EXIT_OK
    width = max((len(r["name"]) for r in rows), default=4)
    for r in rows:
        where = "built-in" if r["builtin"] else r["file"]
        what = (
            f"error: {r['error']}"
            if "error" in r
            else f"{r['vendor']} {r['model']} ({r['points']} points)".lstrip()
        )
        print(f"{r['name']:<{width}}  {what}  [{where}]")
    return EXIT_OK


def _show(args: argparse.Namespace) -> int:
    template = load(args.name)
    points, hints = points_of(template)
    rows = []
    for p in points:
        row: dict[str, Any] = {
            "name": p.name,
            "table": p.table,
            "address": p.address,
            "type": p.type,
        }
        if p.type == "string":
            row["count"] = p.count
        if p.scale != 1 or p.offset != 0:
            row.update(scale=p.scale, offset=p.offset)
        row.update(hints.get(p.name, {}))
        rows.append(row)
    if args.json:
        doc = _summary(template)
        doc.update(
            word_order=template.word_order,
            limits=dict(template.limits),
            response_delay=template.response_delay,
            identify=dict(template.identify),
            address=template.address,
            modes=list(template.modes),
            points=rows,
        )
        if template.probe is not None:
            doc["probe"] = vars(template.probe)
        emit({"ok": True, "template": doc})
        return EXIT_OK
    print(
        f"{template.name}: {template.title}"
        + (f" - {template.description}" if template.description else "")
    )
    print(f"  file: {template.path or template.source}")
    facts = {"word order": template.word_order, "address": template.address,
             "modes": ", ".join(template.modes)}  # fmt: skip
    facts.update({k.replace("_", " "): v for k, v in template.limits.items()})
    if template.response_delay:
        facts["response delay"] = f"{template.response_delay:g} s"
    if template.identify:
        facts["identify"] = ", ".join(f"{k}={v!r}" for k, v in template.identify.items())
    if template.probe is not None:
        pr = template.probe
        facts["probe"] = f"{pr.table} {pr.address} = {pr.value}"
    for k, v in facts.items():
        print(f"  {k}: {v}")
    print(f"  points ({len(rows)}):")
    for r in rows:
        extra = _extras(r)
        print(f"    {r['name']:<20} {r['table']:<15} {r['address']:>5}  {r['type']:<8}{extra}")
    return EXIT_OK


def _extras(row: Mapping[str, Any]) -> str:
    parts = []
    if "scale" in row:
        parts.append(f"x{row['scale']:g}" + (f"{row['offset']:+g}" if row["offset"] else ""))
    if "unit" in row:
        parts.append(str(row["unit"]))
    if row.get("writable"):
        bounds = (
            f" {row.get('min', '')}..{row.get('max', '')}" if "min" in row or "max" in row else ""
        )
        parts.append("writable" + bounds)
    return ("  " + "  ".join(parts)) if parts else ""


def _check(args: argparse.Namespace) -> int:
    from pyrtu.devices.registry import load_template

    results = []
    for name in args.files:
        try:
            template = load_template(name)
            points, _ = points_of(template)
            results.append(
                {"file": name, "ok": True, "name": template.title, "points": len(points)}
            )
        except ValueError as e:
            results.append({"file": name, "ok": False, "error": str(e)})
    bad = [r for r in results if not r["ok"]]
    if args.json:
        emit({"ok": not bad, "exit_code": EXIT_USAGE if bad else EXIT_OK, "files": results})
    else:
        for r in results:
            if r["ok"]:
                print(f"{r['file']}: ok: {r['name']}, {r['points']} points")
            else:
                print(f"pyrtu template: {r['error']}", file=sys.stderr)
    return EXIT_USAGE if bad else EXIT_OK


COMMANDS = (
    subcommand(
        "template",
        "device templates: list, show NAME, check FILE",
        _configure,
        _run,
        __doc__,
    ),
)
