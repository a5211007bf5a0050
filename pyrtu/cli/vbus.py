"""``pyrtu vbus``: a virtual RS-485 bus of pseudo-terminals as its own process
(`pyrtu.vbus.VirtualBus`; docs/vbus.md)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from typing import Any

from pyrtu.cli.common import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_PORT,
    EXIT_USAGE,
    MAX_BAUDRATE,
    CommandSpec,
    baudrate,
    bounded_int,
    finite_float,
    positive_seconds,
    seconds,
    serial_kwargs,
    stop_on_signals,
)

#: a drop count (the cap is the Modbus one: 247 slaves and a master; pyrtu.vbus.MAX_DROPS)
MAX_DROPS = 248
_drops = bounded_int(1, MAX_DROPS, "a number of drops")
_drop = bounded_int(0, MAX_DROPS - 1, "a drop index")
_probability = finite_float(0.0, 1.0, "a probability")
_bytes = bounded_int(0, None, "a byte count")


#: the fault options: flag, the `pyrtu.vbus.Faults` field it sets, type, default,
#: metavar, help
_FAULT_OPTIONS: tuple[tuple[str, str, Callable[[str], Any], Any, str | None, str | None], ...] = (
    ("--seed", "seed", int, 0, None, None),
    ("--bit-flip-rate", "bit_flip_rate", _probability, 0.0, "P", "per bit"),
    ("--drop-rate", "drop_rate", _probability, 0.0, "P", "lost bytes"),
    ("--insert-rate", "insert_rate", _probability, 0.0, "P", "extra bytes"),
    ("--gap-every", "gap_every", _bytes, 0, "N", "gap before every Nth byte"),
    ("--gap-rate", "gap_rate", _probability, 0.0, "P", "random gaps"),
    ("--gap", "gap_s", seconds, 0.0, "SECONDS", "gap length"),
    ("--batch", "batch_s", seconds, 0.0, "SECONDS", "split delivery period"),
    ("--batch-bytes", "batch_bytes", bounded_int(1, None, "a byte count"), 62, "N", None),
)


def _drop_count(text: str) -> tuple[int, int]:
    drop, _, count = text.partition(":")
    try:
        value = int(drop), int(count or "0")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected DROP[:BYTES], not {text!r}") from None
    if value[0] < 0 or value[1] < 0:
        raise argparse.ArgumentTypeError(f"expected DROP[:BYTES] (0 or more), not {text!r}")
    return value


def _configure_vbus(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--drops",
        type=_drops,
        default=2,
        help=f"number of drops, 1..{MAX_DROPS} (default 2; each is a pseudo-terminal)",
    )
    p.add_argument(
        "--baud",
        "--baudrate",
        dest="baudrate",
        type=baudrate,
        metavar="BAUD",
        default=19200,
        help=f"(default 19200; at most {MAX_BAUDRATE})",
    )
    p.add_argument(
        "--parity",
        default="E",
        choices=["N", "E", "O", "n", "e", "o"],
        help="parity of the bus, for timing only (default E: 11-bit characters)",
    )
    p.add_argument("--stopbits", type=int, default=1, choices=[1, 2])
    p.add_argument("--bytesize", type=int, default=8, choices=[7, 8])
    p.add_argument(
        "--dir", default=None, help="directory for the drop0.. symlinks (default: a temp dir)"
    )
    p.add_argument(
        "--echo", type=_drop, nargs="*", default=[], metavar="DROP", help="drops with local echo"
    )
    p.add_argument(
        "--capture",
        metavar="FILE",
        help="write every wire byte to FILE (a FILE that exists and is not empty is "
        "refused, exit 2, unless --overwrite)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="let --capture replace an existing FILE"
    )
    p.add_argument(
        "--duration", type=positive_seconds, metavar="SECONDS", help="stop after this time"
    )
    p.add_argument("--stats", action="store_true", help="print counters on exit (stderr)")
    f = p.add_argument_group("faults (every drop; seeded)")
    for flag, field, convert, default, metavar, text in _FAULT_OPTIONS:
        f.add_argument(flag, dest=field, type=convert, default=default, metavar=metavar, help=text)
    f.add_argument(
        "--unplug",
        type=_drop_count,
        action="append",
        default=[],
        metavar="DROP[:BYTES]",
        help="unplug DROP after it sent BYTES bytes (repeatable)",
    )


def _check_drops(args: argparse.Namespace) -> None:
    """Drop indexes against --drops (argparse checks each option alone)."""
    for flag, drops in (("--echo", args.echo), ("--unplug", [d for d, _ in args.unplug])):
        for drop in drops:
            if drop >= args.drops:
                raise ValueError(f"{flag}: no drop {drop} on a {args.drops}-drop bus (--drops)")


def _check_capture(args: argparse.Namespace) -> None:
    """A capture is not written over an earlier one unless asked (an empty file, as
    ``mktemp`` makes, holds nothing to lose; a device such as /dev/null neither)."""
    path = args.capture
    if path is None or args.overwrite:
        return
    try:
        size = os.stat(path).st_size
    except OSError:
        return  # not there (or not reachable: opening it says why, exit 3)
    if os.path.isfile(path) and size > 0:
        raise ValueError(
            f"--capture {path}: the file exists ({size} bytes); "
            "--overwrite replaces it, or name another file"
        )


def _flag_of(exc: OSError, args: argparse.Namespace) -> str:
    name = str(exc.filename or "")
    if args.capture is not None and name == args.capture:
        return "--capture"
    return "--dir"


def _run_vbus(args: argparse.Namespace) -> int:
    from pyrtu.vbus import BusDirectoryBusy

    try:
        _check_drops(args)
        _check_capture(args)
        return _serve_vbus(args)
    except BusDirectoryBusy as exc:
        print(f"pyrtu vbus: port error: --dir {exc}", file=sys.stderr)
        return EXIT_PORT
    except BrokenPipeError:  # stdout closed (| head -1): the command's end, not --dir's
        raise
    except OSError as exc:
        what = f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc)
        print(f"pyrtu vbus: port error: {_flag_of(exc, args)} {what}", file=sys.stderr)
        return EXIT_PORT
    except ValueError as exc:
        print(f"pyrtu vbus: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


def _serve_vbus(args: argparse.Namespace) -> int:
    from pyrtu.vbus import Faults, VirtualBus

    faults = Faults(**{field: getattr(args, field) for _, field, *_ in _FAULT_OPTIONS})
    with stop_on_signals() as stop:
        with VirtualBus(
            args.drops,
            **serial_kwargs(args),
            directory=args.dir,
            echo=args.echo,
            faults=faults,
            capture=args.capture,
        ) as bus:
            for drop, after in args.unplug:
                bus.unplug(drop, after_bytes=after)
            for path in bus.paths:
                print(path)
            sys.stdout.flush()
            print(
                f"pyrtu vbus: {args.drops} drops, {args.baudrate} baud"
                f" {args.bytesize}{args.parity.upper()}{args.stopbits}"
                f" ({bus.bits} bits/char, {bus.char_time * 1e6:.1f} us/char);"
                " clients open the drops as 8N1 or 8N2; Ctrl-C to stop",
                file=sys.stderr,
                flush=True,
            )
            deadline = None if args.duration is None else time.monotonic() + args.duration
            while not stop.is_set():
                timeout = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
                if timeout <= 0:
                    break
                stop.wait(timeout)
                if bus.error is not None:
                    print(f"pyrtu vbus: error: the hub failed: {bus.error!r}", file=sys.stderr)
                    return EXIT_FAILURE
            if args.stats:
                _print_stats(bus.counters())
    return EXIT_OK


def _print_stats(c: Any) -> None:
    print(
        f"wire_bytes={c.wire_bytes} collisions={c.collisions}"
        f" collided_bytes={c.collided_bytes}" + "".join(f" {k}={v}" for k, v in c.faults.items()),
        file=sys.stderr,
    )
    for i, d in enumerate(c.drops):
        print(
            f"drop{i}: tx={d.tx_bytes} rx={d.rx_bytes} collisions={d.collisions}"
            f" overruns={d.overruns} unheard={d.unheard}"
            f"{' unplugged' if d.unplugged else ''}",
            file=sys.stderr,
        )


COMMANDS = (
    CommandSpec(
        "vbus",
        "run a virtual RS-485 bus of pseudo-terminals",
        _configure_vbus,
        _run_vbus,
        description=(
            "Run a virtual RS-485 bus: prints one drop path per line, then runs until\n"
            "SIGINT/SIGTERM (or --duration).  Open the drops as 8N1/8N2 with any serial\n"
            "library; --parity only sets the character time (pseudo-terminals cannot\n"
            "carry parity).  Fault options apply to every drop."
        ),
    ),
)
