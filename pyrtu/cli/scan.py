"""``pyrtu scan``: which slave addresses answer on a bus.

Every address of ``--range`` gets one probe: FC 03 reading one holding register at
``--register`` (default 0), or the function ``--function`` names.  An answer proves a
device: a normal response, an exception response (the device is there but refuses
that register or function), and a garbled answer (CRC error: a device at that
address with a problem, or two devices answering).  Not an answer: no response
within the timeout, and a gateway's exceptions 0x0A (no path to that unit) and 0x0B
(the device behind it did not respond): no slave is there
(`pyrtu.pdu.errors.ExceptionResponseError.no_device_answered`).

The timeout (``--timeout``) defaults to 0.1 s on a serial line and to 1 s on a
network port (``tcp://``, ``rtu+tcp://``, ``socket://``, ``rfc2217://``): a gateway
answers a silent address only after its own bus timeout, and probes sent meanwhile
wait behind it.  On ``tcp://`` answers that come after the timeout (their
transaction ids tell) are counted and reported ("raise --timeout"): slaves may
have been missed.

On ``tcp://`` the scan first probes unit 248, which no slave can have (serial
addresses are 1..247): a device that answers it ignores the unit id, as a plain
Modbus TCP device may (Messaging on TCP/IP Implementation Guide 4.4.1.2), and would
answer every address of the range.  The scan says so ("the device answers every
unit id") instead of listing each address.

``--identify`` asks every device found for its FC 43 identification and names the
device template it matches (``pyrtu template list``): a template whose ``identify``
the FC 43 objects are, else one whose ``probe`` register reads its value.  Exit status 0
when at least one slave answered, 4 when none did.
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
    describe_format,
    emit,
    open_master,
    register_address,
)
from pyrtu.cli.live_view import fit_line, terminal_size
from pyrtu.drivers._portname import NETWORK_SCHEMES, RTU_TCP_SCHEME, url_scheme
from pyrtu.drivers.links import transport_of

if TYPE_CHECKING:
    from pyrtu.drivers.master import Master

#: the default --timeout on a serial line, and on a network port (`NETWORK_SCHEMES`)
SERIAL_TIMEOUT = 0.1
NETWORK_TIMEOUT = 1.0
#: RTU (or ASCII) frames over a socket: the serial format is the far end's
_RAW_SOCKET_SCHEMES = frozenset((RTU_TCP_SCHEME, "socket"))
#: a unit id no slave can have (serial addresses are 1..247; 248..255 are reserved)
RESERVED_UNIT = 248

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


def _identifiable() -> list[Any]:
    """The templates of the registry with an ``identify`` or a ``probe``; a file
    that is not a template is named in a warning and left out."""
    from pyrtu.devices.registry import TemplateError, entries

    out = []
    for entry in entries().values():
        try:
            template = entry.load()
        except TemplateError as e:
            print(f"pyrtu scan: warning: {e} (left out of --identify)", file=sys.stderr)
            continue
        if template.identify or template.probe is not None:
            out.append(template)
    return out


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
        "--identify",
        action="store_true",
        help="FC 43 identification of each slave found, and the device template it matches",
    )
    add_json_option(p)
    add_serial_options(
        p,
        timeout=SERIAL_TIMEOUT,
        timeout_by_port=f"{SERIAL_TIMEOUT:g} s on a serial line, {NETWORK_TIMEOUT:g} s on "
        "tcp://, udp://, rtu+tcp://, socket://, rfc2217://: more than a gateway's bus timeout",
    )


def default_timeout(scheme: str | None) -> float:
    """``--timeout`` when none is given, for a port of URL ``scheme`` (None: a path)."""
    return NETWORK_TIMEOUT if scheme in NETWORK_SCHEMES else SERIAL_TIMEOUT


def _describe(args: argparse.Namespace, scheme: str | None) -> str:
    """How the port is reached, for the header: the serial format of a serial line
    (and rfc2217://, which sets it), not of a socket."""
    transport = transport_of(args.port)
    if transport.mbap:  # Modbus TCP, Modbus over UDP...
        return transport.what
    if scheme in _RAW_SOCKET_SCHEMES:
        return f"{args.mode.upper()} over TCP"
    return describe_format(args)


def _probe_entry(master: Master, slave: int, args: argparse.Namespace) -> dict[str, Any] | None:
    """What answered a probe of ``slave``, or None when no device did."""
    from pyrtu.pdu.errors import ExceptionResponseError, FrameError, NoResponseError

    entry: dict[str, Any] = {"slave": slave}
    try:
        entry.update(answer="response", detail=probe(master, slave, args.function, args.register))
    except NoResponseError:
        return None
    except ExceptionResponseError as exc:
        if exc.no_device_answered:  # a gateway's 0x0A/0x0B: no device there
            return None
        entry.update(
            answer="exception",
            detail=f"exception {exc.code} ({exc.name})",
            exception_code=exc.code,
        )
    except FrameError as exc:
        entry.update(answer="garbled", detail=str(exc))
    if args.identify:
        ident = identify(master, slave)
        entry["identification"] = ident
        from pyrtu.cli.info import OBJECT_NAMES
        from pyrtu.cli.template import identify_device

        ids = {v: k for k, v in OBJECT_NAMES.items()}
        objects = (
            {ids[k]: v for k, v in ident.items() if k in ids} if isinstance(ident, dict) else {}
        )
        match, how, _ = identify_device(master, slave, args.templates, objects)
        entry["template"] = match.name if match is not None else None
        entry["matched_by"] = how if match is not None else None
    return entry


def _run(args: argparse.Namespace) -> int:
    scheme = url_scheme(args.port)  # ValueError (usage) for a scheme no one opens
    args.templates = []
    if args.identify:  # the registry's templates that say how to recognise them
        args.templates = _identifiable()
    if args.timeout is None:
        args.timeout = default_timeout(scheme)
    found: list[dict[str, Any]] = []
    every: dict[str, Any] | None = None  # the answer of a device that ignores the unit id
    progress = sys.stderr.isatty()
    room = terminal_size(sys.stderr)  # the progress line fits it (no wrap: \r redraws it)
    t0 = time.monotonic()
    addresses: range = args.addresses
    if not args.json:
        print(
            f"scanning slaves {addresses.start}-{addresses.stop - 1} on {args.port} "
            f"({_describe(args, scheme)}, timeout {args.timeout * 1e3:g} ms, "
            f"probe FC {args.function})",
            flush=True,
        )
    with open_master(args) as master:
        if transport_of(args.port).mbap:  # a device that answers every unit id?
            every = _probe_entry(master, RESERVED_UNIT, args)
        for slave in addresses if every is None else ():
            if progress:
                text = fit_line(f"probing {slave}...", room().columns - 1)
                sys.stderr.write(f"\r\x1b[K{text}")
                sys.stderr.flush()
            entry = _probe_entry(master, slave, args)
            if entry is None:
                continue
            found.append(entry)
            if progress:
                sys.stderr.write("\r\x1b[K")
            if not args.json:
                print(_line(entry), flush=True)
        late = master.counters.get("late", 0)
    if progress:
        sys.stderr.write("\r\x1b[K")
        sys.stderr.flush()
    elapsed = time.monotonic() - t0
    ok = bool(found) or every is not None
    if args.json:
        doc: dict[str, Any] = {} if ok else {"error": "no_response", "exit_code": 4}
        if every is not None:
            doc.update(every_unit=True, device=every)
        if late:
            doc["late_answers"] = late
        emit(
            {
                "ok": ok,
                **doc,
                "range": [addresses.start, addresses.stop - 1],
                "function": args.function,
                "found": found,
                "slaves": [e["slave"] for e in found],
                "seconds": round(elapsed, 3),
            }
        )
    elif every is not None:
        print(
            f"the device answers every unit id: unit {RESERVED_UNIT}, which no slave can "
            f"have, {_line(every).split(': ', 1)[1]}"
        )
        print(f"one Modbus TCP device (it ignores the unit id) found in {elapsed:.1f} s")
    else:
        names = ", ".join(str(e["slave"]) for e in found) or "none"
        print(
            f"{len(found)} slave{'s' if len(found) != 1 else ''} found ({names}) in {elapsed:.1f} s"
        )
    if late:
        print(
            f"pyrtu scan: warning: {late} answer{'s' if late != 1 else ''} came after the "
            f"timeout of {args.timeout:g} s (a gateway with a longer bus timeout?): slaves "
            "may have been missed; raise --timeout",
            file=sys.stderr,
        )
    if not ok:
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
    if entry.get("template"):
        line += f"  template {entry['template']} (by {entry['matched_by']})"
    elif "template" in entry:
        line += "  no template matches"
    return line


COMMANDS = (
    subcommand(
        "scan", "find the slaves on a bus (one short probe per address)", _configure, _run, __doc__
    ),
)
