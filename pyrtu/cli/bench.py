"""``pyrtu bench``: what pyrtu gains on this machine, and how good your line is.

Without options, in under a minute: the C core against its pure-Python fallback and
the peers installed here (crcmod, minimalmodbus, pymodbus) on CRC-16, the framer,
`parse_stream` and a master's transaction on the virtual bus (a pyrtu slave in
another process at 115200 baud), with a table on the terminal.

With ``--port PORT`` (a serial port or a ``tcp://``/``rtu+tcp://`` URL) and
``--slave N``: a line check of your own bus: a register read ``--samples`` times,
the round trip's p50 and p99, when the answer starts after the request (the
device's turnaround plus the adapter's latency), whether the adapter holds bytes
back, and the timeout and framing pyrtu recommends for that line
(`pyrtu.bench.line` says how each figure is measured).

``--json``: one JSON document on stdout.  ``--html FILE``: a self-contained report
with plots (a latency histogram, the time line of one transaction), which needs the
optional extra ``pyrtu[bench]`` (matplotlib); checked before anything is measured.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    add_json_option,
    add_seconds_option,
    add_serial_options,
    add_slave_option,
    bounded_int,
    emit,
    register_address,
    serial_kwargs,
)


def _parts(text: str) -> list[str]:
    from pyrtu.bench.suite import PARTS

    if text == "none":
        return []
    names = [t.strip() for t in text.split(",") if t.strip()]
    unknown = [n for n in names if n not in PARTS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"{text!r}: a comma-separated list of {', '.join(PARTS)} (or none)"
        )
    return names


#: the line check's own options (``--NAME``), each the keyword of the same name of both
#: checks (`pyrtu.bench.line`; ``timeout`` comes from the serial options)
_LINE_CHECK_OPTIONS: dict[str, dict[str, Any]] = {
    "table": dict(
        choices=("holding", "input"),
        default="holding",
        help="the registers the line check reads (default holding: FC 03; input: FC 04)",
    ),
    "address": dict(type=register_address, default=0, metavar="ADDR", help="(default 0)"),
    "count": dict(
        type=bounded_int(1, 125, "a register count (1..125)"),
        default=1,
        metavar="N",
        help="registers per read (default 1)",
    ),
    "samples": dict(
        type=bounded_int(1, 100_000, "a number of transactions"),
        default=100,
        metavar="N",
        help="transactions of the line check (default 100)",
    ),
}


def _configure(p: argparse.ArgumentParser) -> None:
    from pyrtu.bench.suite import PARTS

    p.add_argument(
        "--parts",
        type=_parts,
        default=list(PARTS),
        metavar="LIST",
        help=f"what the suite measures: {','.join(PARTS)} (default all; none: the line check only)",
    )
    add_seconds_option(
        p,
        "--budget",
        default=1.5,
        help="time per measurement (default 1.5 s: the suite in well under a minute)",
    )
    p.add_argument("--quick", action="store_true", help="0.3 s per measurement (a rough look)")
    p.add_argument(
        "--port",
        metavar="PORT",
        help="check your own line: a serial port or a tcp://HOST:PORT (rtu+tcp://) URL",
    )
    add_slave_option(p, "the slave the line check reads (default 1)")
    for name, keywords in _LINE_CHECK_OPTIONS.items():
        p.add_argument(f"--{name}", **keywords)
    add_json_option(p)
    p.add_argument("--html", metavar="FILE", help="also write a self-contained HTML report")
    add_serial_options(p)


def _run(args: argparse.Namespace) -> int:
    from pyrtu.bench import line as line_check
    from pyrtu.bench.report import as_html, as_json, plotting_available, table
    from pyrtu.bench.suite import run_suite

    if args.html is not None:
        if not plotting_available():
            print(
                "pyrtu bench: --html needs matplotlib: pip install 'pyrtu[bench]'",
                file=sys.stderr,
            )
            return EXIT_USAGE
        parent = Path(args.html).resolve().parent
        if not parent.is_dir():
            print(f"pyrtu bench: --html {args.html}: no directory {parent}", file=sys.stderr)
            return EXIT_USAGE
    if not args.parts and args.port is None:
        print("pyrtu bench: --parts none leaves nothing to do without --port", file=sys.stderr)
        return EXIT_USAGE
    if args.port is not None and args.slave == 0:
        print("pyrtu bench: --slave 0 is the broadcast: a line check needs 1..247", file=sys.stderr)
        return EXIT_USAGE
    budget = 0.3 if args.quick else args.budget

    def progress(what: str) -> None:
        if not args.json:
            print(f"measuring {what} ...", file=sys.stderr, flush=True)

    suite = run_suite(args.parts, budget, progress) if args.parts else None
    report = None
    if args.port is not None:
        progress(f"the line {args.port}")
        common = {name: getattr(args, name) for name in (*_LINE_CHECK_OPTIONS, "timeout")}
        if "://" in args.port and not args.port.startswith(("loop://", "rfc2217://", "socket://")):
            report = line_check.check_tcp(args.port, args.slave, **common)
        else:
            report = line_check.check_serial(
                args.port, args.slave, **serial_kwargs(args), exclusive=args.exclusive, **common
            )
    if args.json:
        emit(as_json(suite, report))
    else:
        sys.stdout.write(table(suite, report))
    if args.html is not None:
        Path(args.html).write_text(as_html(suite, report), encoding="utf-8")
        if not args.json:
            print(f"report: {args.html}", file=sys.stderr)
    if report is not None and not report.round_trips:
        print(
            f"pyrtu bench: slave {args.slave} on {args.port} never answered: {report.failures[0]}",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    return EXIT_OK


COMMANDS = (
    subcommand(
        "bench",
        "benchmark pyrtu on this machine; check your own line (--port)",
        _configure,
        _run,
        __doc__,
    ),
)
