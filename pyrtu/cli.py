"""The ``pyrtu`` command line (also ``python -m pyrtu``).

Subcommands are registered in `COMMANDS` with `register` (or the `command`
decorator): a name, a one-line help, a function that adds the subcommand's
arguments to its parser, and a function that runs it and returns the exit status.
Modules with heavy imports should import them inside their run function, so that
``pyrtu --help`` stays fast::

    def _configure_read(p: argparse.ArgumentParser) -> None:
        p.add_argument("port")

    @command("read", "read registers from a device", _configure_read)
    def _run_read(args: argparse.Namespace) -> int:
        ...
        return 0
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import FrameType
from typing import Any

__all__ = ["COMMANDS", "Command", "build_parser", "command", "main", "register"]

Configure = Callable[[argparse.ArgumentParser], None]
Run = Callable[[argparse.Namespace], int]


@dataclass(frozen=True)
class Command:
    """A ``pyrtu`` subcommand."""

    name: str
    help: str
    configure: Configure
    run: Run
    description: str | None = None


#: The registered subcommands, in the order they are listed by ``--help``.
COMMANDS: dict[str, Command] = {}


def register(
    name: str, help: str, configure: Configure, run: Run, description: str | None = None
) -> Command:
    """Add (or replace) a subcommand."""
    cmd = Command(name, help, configure, run, description)
    COMMANDS[name] = cmd
    return cmd


def command(
    name: str, help: str, configure: Configure, description: str | None = None
) -> Callable[[Run], Run]:
    """Decorator form of `register` for the run function."""

    def deco(run: Run) -> Run:
        register(name, help, configure, run, description)
        return run

    return deco


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pyrtu", description="Modbus RTU toolkit (pyrtu).")
    try:
        from pyrtu import __version__ as version
    except ImportError:  # pragma: no cover - package half-installed
        version = "unknown"
    parser.add_argument("--version", action="version", version=f"pyrtu {version}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for cmd in COMMANDS.values():
        p = sub.add_parser(
            cmd.name,
            help=cmd.help,
            description=cmd.description or cmd.help,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        cmd.configure(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(list(argv) if argv is not None else None)
    run: Run | None = getattr(args, "_run", None)
    if run is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return run(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head, less, ...
        sys.stderr.close()
        return 0


# -- vbus -------------------------------------------------------------------------


def _drop_count(text: str) -> tuple[int, int]:
    drop, _, count = text.partition(":")
    try:
        return int(drop), int(count or "0")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected DROP[:BYTES], got {text!r}") from None


def _configure_vbus(p: argparse.ArgumentParser) -> None:
    p.add_argument("--drops", type=int, default=2, help="number of drops (default 2)")
    p.add_argument("--baud", type=int, default=19200, help="baud rate (default 19200)")
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
        "--echo", type=int, nargs="*", default=[], metavar="DROP", help="drops with local echo"
    )
    p.add_argument("--capture", metavar="FILE", help="write every wire byte to FILE")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--stats", action="store_true", help="print counters on exit (stderr)")
    f = p.add_argument_group("faults (every drop; seeded)")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--bit-flip-rate", type=float, default=0.0, metavar="P", help="per bit")
    f.add_argument("--drop-rate", type=float, default=0.0, metavar="P", help="lost bytes")
    f.add_argument("--insert-rate", type=float, default=0.0, metavar="P", help="extra bytes")
    f.add_argument(
        "--gap-every", type=int, default=0, metavar="N", help="gap before every Nth byte"
    )
    f.add_argument("--gap-rate", type=float, default=0.0, metavar="P", help="random gaps")
    f.add_argument("--gap", type=float, default=0.0, metavar="SECONDS", help="gap length")
    f.add_argument(
        "--batch", type=float, default=0.0, metavar="SECONDS", help="split delivery period"
    )
    f.add_argument("--batch-bytes", type=int, default=62, metavar="N")
    f.add_argument(
        "--unplug",
        type=_drop_count,
        action="append",
        default=[],
        metavar="DROP[:BYTES]",
        help="unplug DROP after it sent BYTES bytes (repeatable)",
    )


def _run_vbus(args: argparse.Namespace) -> int:
    try:
        return _serve_vbus(args)
    except (ValueError, IndexError) as exc:
        print(f"pyrtu vbus: {exc}", file=sys.stderr)
        return 2


def _serve_vbus(args: argparse.Namespace) -> int:
    from pyrtu.vbus import Faults, VirtualBus

    faults = Faults(
        seed=args.seed,
        bit_flip_rate=args.bit_flip_rate,
        drop_rate=args.drop_rate,
        insert_rate=args.insert_rate,
        gap_every=args.gap_every,
        gap_rate=args.gap_rate,
        gap_s=args.gap,
        batch_s=args.batch,
        batch_bytes=args.batch_bytes,
    )
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old: dict[signal.Signals, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, on_signal)
    try:
        with VirtualBus(
            args.drops,
            baudrate=args.baud,
            parity=args.parity,
            stopbits=args.stopbits,
            bytesize=args.bytesize,
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
                f"pyrtu vbus: {args.drops} drops, {args.baud} baud"
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
                    print(f"pyrtu vbus: hub failed: {bus.error!r}", file=sys.stderr)
                    return 1
            if args.stats:
                _print_stats(bus.counters())
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0


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


register(
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
)


# -- demo -------------------------------------------------------------------------


def _configure_demo(p: argparse.ArgumentParser) -> None:
    from .demo import configure

    configure(p)


def _run_demo(args: argparse.Namespace) -> int:
    from .demo import run

    return run(args)


register(
    "demo",
    "a short demonstration on simulated devices (no hardware needed)",
    _configure_demo,
    _run_demo,
)
