"""``pyrtu info``: a slave's device identification (FC 43 / MEI 14).

``--level basic`` (read code 1: vendor, product code, revision; the default),
``regular`` (2), ``extended`` (3), or ``--object ID`` (read code 4: one object).
Drives that have no FC 43 (the CV100, the Bonfiglioli Vectron) answer exception 1;
``--profile NAME`` (a device template: ``pyrtu template list``) identifies them the
way their manual allows instead (parameters, status registers); a template without
such code says whether the device is that template's model (its FC 43 ``identify``,
else its ``probe`` register).
"""

from __future__ import annotations

import argparse
from typing import Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_OK,
    add_json_option,
    add_serial_options,
    add_slave_option,
    emit,
    object_id,
    open_master,
)
from pyrtu.cli.template import add_profile_option, identify_device

#: the object names of the Modbus Application Protocol, table of 6.21
OBJECT_NAMES = {
    0: "VendorName",
    1: "ProductCode",
    2: "MajorMinorRevision",
    3: "VendorUrl",
    4: "ProductName",
    5: "ModelName",
    6: "UserApplicationName",
}
LEVELS = {"basic": 1, "regular": 2, "extended": 3}


def _text(value: bytes) -> str:
    return value.decode("ascii", "replace")


def profile_identify(master: Any, device: str, slave: int) -> dict[str, str]:
    """Identification through a device template: its profile's ``identify()`` (the
    drives of the manuals), else whether the device matches the template."""
    from pyrtu.devices.registry import find_template

    template = find_template(device)
    profile = template.hook("profile")
    if profile is not None:
        found: dict[str, Any] = profile(master, slave).identify()
        return {str(k): str(v) for k, v in found.items()}
    match, how, objects = identify_device(master, slave, [template])
    out = {OBJECT_NAMES.get(k, f"object_{k}"): v for k, v in objects.items()}
    out["template"] = template.name
    out["matches"] = "yes" if match is not None else "no"
    out["matched_by"] = how if match is not None else ""
    if match is None:
        out["why"] = how
    return {k: v for k, v in out.items() if v != ""}


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("port", metavar="PORT", help="serial device or pyserial URL")
    add_slave_option(p)
    p.add_argument(
        "--level",
        choices=sorted(LEVELS, key=LEVELS.__getitem__),
        default="basic",
        help="identification category (default basic)",
    )
    p.add_argument("--object", type=object_id, metavar="ID", help="read one object (read code 4)")
    add_profile_option(
        p, "identify through a device template instead of FC 43 (pyrtu template list)"
    )
    add_json_option(p)
    add_serial_options(p)


def _run(args: argparse.Namespace) -> int:
    from pyrtu.devices.registry import names
    from pyrtu.pdu.errors import ExceptionResponseError

    if args.slave == 0:
        raise ValueError("identification needs a slave address 1..247")
    with open_master(args) as master:
        if args.profile:
            ident = profile_identify(master, args.profile, args.slave)
            if args.json:
                emit(
                    {
                        "ok": True,
                        "slave": args.slave,
                        "profile": args.profile,
                        "identification": ident,
                    }
                )
            else:
                print(f"slave {args.slave} ({args.profile} profile):")
                width = max(len(k) for k in ident) if ident else 0
                for key, value in ident.items():
                    print(f"  {key + ':':<{width + 1}} {value}")
            return EXIT_OK
        code, first = (4, args.object) if args.object is not None else (LEVELS[args.level], 0)
        try:
            objects = master.read_device_identification(args.slave, code, first)
        except ExceptionResponseError as exc:
            if exc.code == 1:
                exc.args = (
                    f"{exc}; this device has no FC 43 identification: try --profile NAME "
                    f"({', '.join(names())})",
                )
            raise
    rows: list[dict[str, Any]] = [
        {"id": k, "name": OBJECT_NAMES.get(k, f"object 0x{k:02X}"), "value": _text(v)}
        for k, v in sorted(objects.items())
    ]
    if args.json:
        emit(
            {
                "ok": True,
                "slave": args.slave,
                "read_code": code,
                "objects": rows,
                "identification": {r["name"]: r["value"] for r in rows},
            }
        )
    else:
        level = f"object {args.object}" if args.object is not None else args.level
        print(f"slave {args.slave} device identification ({level}):")
        width = max(len(r["name"]) for r in rows) + 8 if rows else 0
        for r in rows:
            label = f"{r['name']} (0x{r['id']:02X}):"
            print(f"  {label:<{width}} {r['value']}")
    return EXIT_OK


COMMANDS = (
    subcommand("info", "device identification of a slave (FC 43/14)", _configure, _run, __doc__),
)
