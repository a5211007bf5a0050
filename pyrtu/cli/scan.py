"""``pyrtu scan``: which slave addresses answer on a bus.

Every address of ``--range`` gets one probe with a short timeout (default 0.1 s):
FC 03 reading one holding register at ``--register`` (default 0), or the function
``--function`` names.  Any answer proves a device: a normal response, an exception
response (the device is there but refuses that register or function), and a
garbled answer (CRC error: a device at that address with a problem, or two
devices answering).  ``--identify`` asks every device found for its FC 43
identification.  Exit status 0 when at least one slave answered, 4 when none did.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_NO_RESPONSE,
    EXIT_OK,
    add_json_option,
    add_serial_options,
    emit,
    open_master,
    register_address,
)
from pyrtu.cli.live_view import fit_line, terminal_size

if TYPE_CHECKING:
    from pyrtu.drivers.master import Master

PROBES = {
    3: "read holding register",
    4: "read input register",
    1: "read coil",
    2: "read discrete input",
    8: "diagnostics: return query data",
    17: "report server id",
    43: "read device identification",
}


def address_range(text: str) -> range:
    """``"1-247"``, ``"5"`` or ``"1-10"`` (argparse type)."""
    first, sep, last = text.partition("-")
    try:
        lo = int(first, 0)
        hi = int(last, 0) if sep else lo
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected FIRST-LAST (e.g. 1-247), not {text!r}"
        ) from None
    if not 1 <= lo <= hi <= 247:
        raise argparse.ArgumentTypeError(f"a range of slave addresses in 1..247, not {text!r}")
    return range(lo, hi + 1)


def probe(master: Master, slave: int, function: int, register: int) -> str:
    """One probe; returns what answered (raises NoResponseError if nothing did)."""
    if function == 3:
        value = master.read_holding_registers(slave, register, 1)[0]
        return f"holding register {register} = {value} (0x{value:04X})"
    if function == 4:
        value = master.read_input_registers(slave, register, 1)[0]
        return f"input register {register} = {value} (0x{value:04X})"
    if function == 1:
        return f"coil {register} = {int(master.read_coils(slave, register, 1)[0])}"
    if function == 2:
        return (
            f"discrete input {register} = {int(master.read_discrete_inputs(slave, register, 1)[0])}"
        )
    if function == 8:
        echo = master.diagnostics(slave, 0, 0xA55A)
        return f"diagnostics echo 0x{echo:04X}"
    if function == 17:
        return f"server id {master.report_server_id(slave).hex(' ')}"
    objects = master.read_device_identification(slave)
    return "identification " + " ".join(v.decode("ascii", "replace") for v in objects.values())


def identify(master: Master, slave: int) -> dict[str, str] | str:
    """FC 43 basic objects by name, or why there are none."""
    from pyrtu.cli.info import OBJECT_NAMES
    from pyrtu.pdu.errors import ExceptionResponseError, ModbusError

    try:
        objects = master.read_device_identification(slave)
    except ExceptionResponseError as exc:
        return f"exception {exc.code} ({exc.name})"
    except ModbusError as exc:
        return str(exc)
    return {
        OBJECT_NAMES.get(k, f"object_{k}"): v.decode("ascii", "replace") for k, v in objects.items()
    }


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("port", metavar="PORT", help="serial device or pyserial URL")
    p.add_argument(
        "--range",
        dest="addresses",
        type=address_range,
        default=range(1, 248),
        metavar="FIRST-LAST",
        help="slave addresses to probe (default 1-247)",
    )
    p.add_argument(
        "-f",
        "--function",
        type=int,
        default=3,
        choices=sorted(PROBES),
        help="probe function (default 3: read one holding register)",
    )
    p.add_argument(
        "--register",
        type=register_address,
        default=0,
        metavar="ADDRESS",
        help="register or bit to read",
    )
    p.add_argument(
        "--identify", action="store_true", help="FC 43 identification of each slave found"
    )
    add_json_option(p)
    add_serial_options(p, timeout=0.1)


def _run(args: argparse.Namespace) -> int:
    from pyrtu.pdu.errors import ExceptionResponseError, FrameError, NoResponseError

    found: list[dict[str, Any]] = []
    progress = sys.stderr.isatty()
    room = terminal_size(sys.stderr)  # the progress line fits it (no wrap: \r redraws it)
    t0 = time.monotonic()
    addresses: range = args.addresses
    if not args.json:
        print(
            f"scanning slaves {addresses.start}-{addresses.stop - 1} on {args.port} "
            f"({args.baudrate} baud {args.bytesize}{args.parity}{args.stopbits:g}, "
            f"timeout {args.timeout * 1e3:g} ms, probe FC {args.function})",
            flush=True,
        )
    with open_master(args) as master:
        for slave in addresses:
            if progress:
                text = fit_line(f"probing {slave}...", room().columns - 1)
                sys.stderr.write(f"\r\x1b[K{text}")
                sys.stderr.flush()
            entry: dict[str, Any] = {"slave": slave}
            try:
                entry.update(
                    answer="response", detail=probe(master, slave, args.function, args.register)
                )
            except NoResponseError:
                continue
            except ExceptionResponseError as exc:
                entry.update(
                    answer="exception",
                    detail=f"exception {exc.code} ({exc.name})",
                    exception_code=exc.code,
                )
            except FrameError as exc:
                entry.update(answer="garbled", detail=str(exc))
            if args.identify:
                entry["identification"] = identify(master, slave)
            found.append(entry)
            if progress:
                sys.stderr.write("\r\x1b[K")
            if not args.json:
                print(_line(entry), flush=True)
    if progress:
        sys.stderr.write("\r\x1b[K")
        sys.stderr.flush()
    elapsed = time.monotonic() - t0
    if args.json:
        doc: dict[str, Any] = {} if found else {"error": "no_response", "exit_code": 4}
        emit(
            {
                "ok": bool(found),
                **doc,
                "range": [addresses.start, addresses.stop - 1],
                "function": args.function,
                "found": found,
                "slaves": [e["slave"] for e in found],
                "seconds": round(elapsed, 3),
            }
        )
    else:
        names = ", ".join(str(e["slave"]) for e in found) or "none"
        print(
            f"{len(found)} slave{'s' if len(found) != 1 else ''} found ({names}) in {elapsed:.1f} s"
        )
    if not found:
        print("pyrtu scan: no response: no slave answered", file=sys.stderr)
        return EXIT_NO_RESPONSE
    return EXIT_OK


def _line(entry: dict[str, Any]) -> str:
    how = {"response": "answered", "exception": "answered", "garbled": "garbled answer:"}
    line = f"slave {entry['slave']:3d}: {how[entry['answer']]} {entry['detail']}"
    ident = entry.get("identification")
    if isinstance(ident, dict):
        line += "  [" + " ".join(ident.values()) + "]"
    elif isinstance(ident, str):
        line += f"  [FC 43: {ident}]"
    return line


COMMANDS = (
    subcommand(
        "scan", "find the slaves on a bus (one short probe per address)", _configure, _run, __doc__
    ),
)
