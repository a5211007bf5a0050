"""``pyrtu read`` and ``pyrtu write``: one transaction (or a few) with typed values.

Addresses are protocol (PDU) addresses, from 0: the WEG parameter P0680 is 680, the
CV100 code A3.02 is 0x0302 (hexadecimal is accepted).  mbpoll's and modpoll's
references count from 1 (register 40001 is address 0).

Types of registers (the poller's, `pyrtu.pdu.codecs`): ``uint16`` (the default),
``int16``, ``int8``/``uint8`` (a byte of each register: ``--order high``, the
default, or ``low``), ``uint32``, ``int32``, ``float32``, ``bcd32`` (two registers
each), ``uint64``, ``int64``, ``float64`` (four), ``float16``, ``bcd16`` (one),
``string`` (two characters per register, the first in the high byte) and
``string1`` (one character per register, in its low byte).  ``--order``: ABCD
big-endian, CDAB word swap, BADC byte swap, DCBA little-endian (the 64-bit names
ABCDEFGH, GHEFCDAB, BADCFEHG, HGFEDCBA too; a 32-bit name means its 64-bit
equivalent on a 64-bit type); BADC and DCBA (or BA) swap the bytes of one-register
types and strings.  Coils and discrete inputs are bits.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_OK,
    add_json_option,
    add_serial_options,
    add_slave_option,
    emit,
    integer,
    open_master,
    register_address,
    show_address,
)
from pyrtu.cli.template import add_profile_option, register_notes
from pyrtu.pdu import FUNCTION_NAMES, codecs

if TYPE_CHECKING:
    from pyrtu.drivers.master import Master

#: table name -> (read function, write functions single/multiple, what it holds)
TABLES: dict[str, tuple[int, tuple[int, int] | None, str]] = {
    "holding": (3, (6, 16), "holding registers"),
    "input": (4, None, "input registers"),
    "coils": (1, (5, 15), "coils"),
    "discrete": (2, None, "discrete inputs"),
}
_TABLE_ALIASES = {
    "holding": "holding",
    "hr": "holding",
    "4x": "holding",
    "input": "input",
    "ir": "input",
    "3x": "input",
    "coils": "coils",
    "coil": "coils",
    "co": "coils",
    "0x": "coils",
    "discrete": "discrete",
    "di": "discrete",
    "1x": "discrete",
}
TYPES = tuple(t for t in codecs.TYPES if t != "bool")
ORDERS = codecs.ORDERS

Value = int | float | str | bool | None


def _add_item_options(p: argparse.ArgumentParser, slave_help: str, table_help: str) -> None:
    """-a/--slave, -T/--table, --type and --order, shared by read and write."""
    add_slave_option(p, slave_help)
    p.add_argument("-T", "--table", type=table, default="holding", metavar="TABLE", help=table_help)
    p.add_argument(
        "-t", "--type", dest="kind", default="uint16", choices=TYPES, help="(default uint16)"
    )
    p.add_argument(
        "--order",
        type=order,
        default="ABCD",
        metavar="ORDER",
        help="word/byte order: ABCD (default), CDAB, BADC, DCBA (64-bit: ABCDEFGH, GHEFCDAB,"
        " BADCFEHG, HGFEDCBA); 8-bit types: high (default), low",
    )


def table(text: str) -> str:
    try:
        return _TABLE_ALIASES[text.lower()]
    except KeyError:
        raise argparse.ArgumentTypeError(
            f"table is holding, input, coils or discrete, not {text!r}"
        ) from None


def order(text: str) -> str:
    value = text.lower() if text.lower() in codecs.ORDERS_8 else text.upper()
    if value not in ORDERS:
        raise argparse.ArgumentTypeError(f"order is one of {', '.join(ORDERS)}, not {text!r}")
    return value


def type_order(kind: str, text: str) -> str:
    """The order ``kind`` uses for ``--order`` (ValueError naming the flag)."""
    try:
        return codecs.normalize_order(kind, text)
    except ValueError as e:
        raise ValueError(f"--order: {e}") from None


def is_bits(table_name: str) -> bool:
    return table_name in ("coils", "discrete")


def width(kind: str) -> int:
    """Registers per value (a string: per character pair or character)."""
    return codecs.CODECS[kind].registers or 1


def is_text(kind: str) -> bool:
    return codecs.CODECS[kind].kind == "str"


# -- decoding -------------------------------------------------------------------------------


def decode(kind: str, registers: Sequence[int], word_order: str) -> list[Value]:
    """Registers as values of ``kind`` (a string is one value; None: no number, a BCD
    digit above 9)."""
    regs = list(registers)
    if is_text(kind):
        return [codecs.decoder(kind, type_order(kind, word_order), len(regs))(regs, 0)]
    read = codecs.decoder(kind, type_order(kind, word_order))
    step = width(kind)
    return [read(regs, i) for i in range(0, len(regs) - step + 1, step)]


def encode(kind: str, texts: Sequence[str], word_order: str) -> tuple[list[int], list[Value]]:
    """Command-line values as registers (and the values they stand for)."""
    layout = type_order(kind, word_order)
    if is_text(kind):
        text = " ".join(texts)
        per = 2 if kind == "string" else 1
        count = -(-len(text.encode("latin-1", "replace")) // per)  # 0 for "": nothing
        return codecs.encoder(kind, layout, count)(text), [text]
    values: list[Value] = [_number(kind, t) for t in texts]
    write = codecs.encoder(kind, layout)
    out: list[int] = []
    for v in values:
        out += write(v)
    return out, values


def _number(kind: str, text: str) -> int | float:
    codec = codecs.CODECS[kind]
    if codec.kind == "float":
        try:
            return float(text)
        except ValueError:
            raise ValueError(f"{kind} value expected, not {text!r}") from None
    try:
        value = int(text, 0)
    except ValueError:
        raise ValueError(f"{kind} value expected (decimal or 0x hex), not {text!r}") from None
    lo, hi = codec.low, codec.high
    if not lo <= value <= hi:
        hint = ""
        if kind.startswith("u") and value < 0:
            hint = f"; use --type {kind[1:]} for negative values"
        raise ValueError(f"{kind} is {lo}..{hi}, not {value}{hint}")
    return value


_TRUE = {"1", "on", "true", "yes", "t", "y"}
_FALSE = {"0", "off", "false", "no", "f", "n"}


def parse_bit(text: str) -> bool:
    t = text.strip().lower()
    if t in _TRUE:
        return True
    if t in _FALSE:
        return False
    raise ValueError(f"a bit is 1/0, on/off or true/false, not {text!r}")


def show(value: Value, kind: str) -> str:
    """A value for people."""
    if value is None:
        return "(no number: a BCD digit above 9)"
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return f"{value:.7g}"
    if isinstance(value, str):
        return repr(value)
    if kind in ("uint8", "int8"):
        return f"{value} (0x{value & 0xFF:02X})"
    if kind in ("uint16", "int16"):
        return f"{value} (0x{value & 0xFFFF:04X})"
    if kind in ("uint32", "int32"):
        return f"{value} (0x{value & 0xFFFF_FFFF:08X})"
    if kind in ("uint64", "int64"):
        return f"{value} (0x{value & 0xFFFF_FFFF_FFFF_FFFF:016X})"
    return str(value)


# -- reading --------------------------------------------------------------------------------


@dataclass
class ReadResult:
    """What one read returned."""

    slave: int
    table: str
    address: int
    kind: str
    order: str
    raw: list[int] | list[bool]
    values: list[Value]
    notes: dict[int, str] = field(default_factory=dict)

    def addresses(self) -> list[int]:
        if not is_bits(self.table) and is_text(self.kind):
            return [self.address]
        step = 1 if is_bits(self.table) else width(self.kind)
        return [int(self.address) + i * step for i in range(len(self.values))]

    def lines(self) -> list[str]:
        out = []
        kind = "bit" if is_bits(self.table) else self.kind
        for addr, value in zip(self.addresses(), self.values, strict=True):
            text = f"[{show_address(addr, self.address)}] {show(value, kind)}"
            note = self.notes.get(addr)
            out.append(f"{text:<24}  {note}" if note else text)
        return out

    def json_values(self) -> list[Value]:
        """The values as JSON carries them: a float32 (float16) as the shortest
        decimal that is the register's value (5.1, not 5.099999904632568;
        pyrtu.poller.values); NaN and the infinities as the strings "nan", "inf",
        "-inf" (JSON has no such numbers)."""
        out: list[Value] = []
        for v in self.values:
            if isinstance(v, float) and not math.isfinite(v):
                out.append(str(v))
            elif isinstance(v, float) and self.kind in ("float32", "float16"):
                from pyrtu.poller.values import shortest_float16, shortest_float32

                out.append((shortest_float16 if self.kind == "float16" else shortest_float32)(v))
            else:
                out.append(v)
        return out

    def document(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "ok": True,
            "slave": self.slave,
            "table": self.table,
            "address": int(self.address),
            "count": len(self.values),
            "type": "bit" if is_bits(self.table) else self.kind,
        }
        if not is_bits(self.table):
            doc["order"] = self.order
            doc["registers"] = list(self.raw)
        doc["values"] = self.json_values()
        doc["addresses"] = self.addresses()
        if self.notes:
            doc["notes"] = {str(k): v for k, v in self.notes.items()}
        return doc


def add_read_arguments(p: argparse.ArgumentParser) -> None:
    """PORT --slave --table ADDRESS [COUNT] --type --order --profile (read and poll)."""
    p.add_argument("port", metavar="PORT", help="serial device (/dev/ttyUSB0) or pyserial URL")
    p.add_argument(
        "address",
        type=register_address,
        metavar="ADDRESS",
        help="first address, 0..65535 (0x hex too)",
    )
    p.add_argument(
        "count",
        type=integer,
        nargs="?",
        default=None,
        metavar="COUNT",
        help="how many values (default 1; string: how many registers, default 1)",
    )
    _add_item_options(p, "slave address (default 1)", "holding (default), input, coils or discrete")
    add_profile_option(
        p,
        "name registers in a device template's terms (a template name or a .toml file;"
        " e.g. P680 of a cfw701): pyrtu template list",
    )


#: the most one request reads or writes (Application Protocol V1.1b, 6.1-6.4, 6.11-6.12)
READ_LIMIT = {"bits": 2000, "registers": 125}
WRITE_LIMIT = {"bits": 1968, "registers": 123}


def check_span(table: str, address: int, n: int, limits: dict[str, int] | None, what: str) -> None:
    """The items a request covers, in the command's terms (ValueError: usage);
    ``limits``: READ_LIMIT, WRITE_LIMIT, or None (one request per item)."""
    unit = "bits" if is_bits(table) else "registers"
    if limits is not None and n > limits[unit]:
        verb = "writes" if limits is WRITE_LIMIT else "reads"
        raise ValueError(f"{what} covers {n} {unit}; one request {verb} at most {limits[unit]}")
    if address + n > 0x10000:
        raise ValueError(f"ADDRESS {address} + {n} {unit} runs past the last address 65535")


def check_read(args: argparse.Namespace) -> None:
    """The read's arguments, checked before the port is opened (ValueError: usage)."""
    if args.slave == 0:
        raise ValueError("a read needs a slave address 1..247 (0 is broadcast: nobody answers)")
    if getattr(args, "profile", None):
        from pyrtu.cli.template import load

        load(args.profile)  # the template's errors before a byte is sent
    count = 1 if args.count is None else args.count
    if count < 1:
        raise ValueError(f"COUNT must be at least 1, not {count}")
    if not is_bits(args.table):
        type_order(args.kind, args.order)
    n = count if is_bits(args.table) or is_text(args.kind) else count * width(args.kind)
    what = f"COUNT {count}" + ("" if is_bits(args.table) else f" of {args.kind}")
    check_span(args.table, args.address, n, READ_LIMIT, what)


def read_values(master: Master, args: argparse.Namespace) -> ReadResult:
    """One read as the arguments say."""
    check_read(args)
    count = 1 if args.count is None else args.count
    tbl = args.table
    if is_bits(tbl):
        reader = master.read_coils if tbl == "coils" else master.read_discrete_inputs
        bits = reader(args.slave, args.address, count)
        return ReadResult(args.slave, tbl, args.address, "bit", args.order, bits, list(bits))
    n = count if is_text(args.kind) else count * width(args.kind)
    reader16 = master.read_holding_registers if tbl == "holding" else master.read_input_registers
    regs = reader16(args.slave, args.address, n)
    result = ReadResult(
        args.slave,
        tbl,
        args.address,
        args.kind,
        args.order,
        regs,
        decode(args.kind, regs, args.order),
    )
    if args.profile:
        result.notes = profile_notes(args.profile, args.address, regs, args.table)
    return result


def profile_notes(
    device: str, address: int, registers: Sequence[int], table: str
) -> dict[int, str]:
    """The registers in the terms of template ``device`` (`register_notes`)."""
    return register_notes(device, address, list(registers), table)


def _configure_read(p: argparse.ArgumentParser) -> None:
    add_read_arguments(p)
    add_json_option(p)
    add_serial_options(p)


def _run_read(args: argparse.Namespace) -> int:
    check_read(args)
    with open_master(args) as master:
        result = read_values(master, args)
    if args.json:
        emit(result.document())
    else:
        print("\n".join(result.lines()))
    return EXIT_OK


# -- writing --------------------------------------------------------------------------------


def _configure_write(p: argparse.ArgumentParser) -> None:
    p.add_argument("port", metavar="PORT", help="serial device (/dev/ttyUSB0) or pyserial URL")
    p.add_argument(
        "address", type=register_address, metavar="ADDRESS", help="first address, 0..65535"
    )
    p.add_argument(
        "values",
        nargs="+",
        metavar="VALUE",
        help="values of --type (registers) or bits 1/0/on/off (coils); a string is one value",
    )
    _add_item_options(
        p,
        "slave address (default 1; 0 broadcasts)",
        "holding (default) or coils (input registers and discrete inputs are read-only)",
    )
    p.add_argument(
        "-f",
        "--function",
        type=int,
        choices=[5, 6, 15, 16],
        help="force the function: 5/6 write one item per transaction, 15/16 all in one "
        "(default: 5 or 6 for one item, 15 or 16 for several)",
    )
    add_json_option(p)
    add_serial_options(p)


@dataclass
class WritePlan:
    table: str
    function: int
    items: list[int] | list[bool]
    values: list[Value]


def plan_write(args: argparse.Namespace) -> WritePlan:
    """Values and function of a write (ValueError: a usage error)."""
    tbl = args.table
    functions = TABLES[tbl][1]
    if functions is None:
        raise ValueError(f"{TABLES[tbl][2]} are read-only: no Modbus function writes them")
    single, multiple = functions
    items: list[int] | list[bool]
    if is_bits(tbl):
        bits = [parse_bit(v) for v in args.values]
        items = bits
        values: list[Value] = list(bits)
    else:
        items, values = encode(args.kind, args.values, args.order)
    function = args.function or (single if len(items) == 1 else multiple)
    if function not in functions:
        raise ValueError(
            f"function {function} ({FUNCTION_NAMES[function]}) does not write {TABLES[tbl][2]}; "
            f"use {single} or {multiple}"
        )
    if not items:
        raise ValueError("VALUE: nothing to write")
    n = len(items)
    limits = WRITE_LIMIT if function == multiple else None
    check_span(tbl, args.address, n, limits, f"VALUE ({n} items)")
    return WritePlan(tbl, function, items, values)


def execute_write(master: Master, slave: int, address: int, plan: WritePlan) -> int:
    """Run the plan; returns the number of transactions."""
    f = plan.function
    if f == 16:
        master.write_registers(slave, address, [int(v) for v in plan.items])
        return 1
    if f == 15:
        master.write_coils(slave, address, [bool(v) for v in plan.items])
        return 1
    for i, item in enumerate(plan.items):
        if f == 6:
            master.write_register(slave, address + i, int(item))
        else:
            master.write_coil(slave, address + i, bool(item))
    return len(plan.items)


def _run_write(args: argparse.Namespace) -> int:
    plan = plan_write(args)
    with open_master(args) as master:
        transactions = execute_write(master, args.slave, args.address, plan)
    first = show_address(args.address, args.address)
    last = args.address + len(plan.items) - 1
    where = first if last == args.address else f"{first}..{show_address(last, args.address)}"
    if args.json:
        doc: dict[str, Any] = {
            "ok": True,
            "slave": args.slave,
            "table": plan.table,
            "address": int(args.address),
            "function": plan.function,
            "function_name": FUNCTION_NAMES[plan.function],
            "transactions": transactions,
            "values": plan.values,
        }
        if not is_bits(plan.table):
            doc["type"] = args.kind
            doc["order"] = args.order
            doc["registers"] = list(plan.items)
        emit(doc)
    else:
        n = len(plan.items)
        what = TABLES[plan.table][2] if n > 1 else TABLES[plan.table][2][:-1]
        kind = "bit" if is_bits(plan.table) else args.kind
        shown = ", ".join(show(v, kind) for v in plan.values)
        target = "broadcast" if args.slave == 0 else f"slave {args.slave}"
        print(
            f"{target}: wrote {n} {what} at {where} = {shown} "
            f"({FUNCTION_NAMES[plan.function]}, FC {plan.function}"
            f"{f', {transactions} transactions' if transactions > 1 else ''})"
        )
    return EXIT_OK


_EPILOG = __doc__.split("\n\n", 1)[1] if __doc__ else ""

COMMANDS = (
    subcommand(
        "read",
        "read registers or bits of a slave (FC 01-04), typed",
        _configure_read,
        _run_read,
        "Read registers (FC 03/04) or bits (FC 01/02) of a slave and print them, typed.\n\n"
        + _EPILOG
        + "\nexample: pyrtu read /dev/ttyUSB0 --slave 1 680 2 --profile cfw701",
    ),
    subcommand(
        "write",
        "write registers or coils of a slave (FC 05/06/15/16), typed",
        _configure_write,
        _run_write,
        "Write holding registers (FC 06 one, FC 16 several) or coils (FC 05 one, FC 15\n"
        "several); --function forces one.\n\n"
        + _EPILOG
        + "\nexample: pyrtu write /dev/ttyUSB0 --slave 1 --type float32 --order CDAB 100 1.5",
    ),
)
