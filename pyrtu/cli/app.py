"""The ``pyrtu`` command line's registry and entry point: `COMMANDS`, `register`,
`command`, `build_parser`, `main` (the package `pyrtu.cli` re-exports them; its
docstring says how a subcommand is added and which module holds which command)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from pyrtu._startup import started
from pyrtu.cli import poll_config
from pyrtu.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    JsonErrorParser,
    exit_code_table,
    silence_stdout,
)
from pyrtu.core._deprecated import renamed

__all__ = ["COMMANDS", "Subcommand", "build_parser", "command", "main", "register"]

Configure = Callable[[argparse.ArgumentParser], None]
Run = Callable[[argparse.Namespace], int]


@dataclass(frozen=True)
class Subcommand:
    """A ``pyrtu`` subcommand."""

    name: str
    help: str
    configure: Configure
    run: Run
    description: str | None = None


#: The registered subcommands, in the order they are listed by ``--help``.
COMMANDS: dict[str, Subcommand] = {}


def register(
    name: str, help: str, configure: Configure, run: Run, description: str | None = None
) -> Subcommand:
    """Add (or replace) a subcommand."""
    cmd = Subcommand(name, help, configure, run, description)
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


def version_line() -> str:
    """``pyrtu --version``: the version (pyrtu/_version.py, the one source) and the backend
    that runs, e.g. "pyrtu 0.1.0 (backend c)"."""
    from pyrtu._version import __version__
    from pyrtu.core import _backend

    return f"pyrtu {__version__} ({_backend.describe()})"


def build_parser() -> argparse.ArgumentParser:
    parser = JsonErrorParser(
        prog="pyrtu",
        description="Modbus RTU toolkit (pyrtu): read, write, poll, scan, identify, sniff, "
        "simulate drives, run a virtual RS-485 bus, and a demo without hardware.\n\n"
        "Many points on many buses: pyrtu poll --config points.toml (the poller; "
        "--duration S, --json).\nEach command's options: pyrtu COMMAND --help.",
        epilog=exit_code_table(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=version_line())
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="log what pyrtu does on stderr (-vv: every frame sent and received)",
    )
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
    argv = list(argv) if argv is not None else sys.argv[1:]
    if poll_config.wants(argv):  # ``pyrtu poll --config FILE``: the poller
        return poll_config.main(argv, _logging)  # (it ends the start-up itself)
    parser = build_parser()
    JsonErrorParser.json_errors = "--json" in argv
    args = parser.parse_args(argv)
    _logging(args.verbose)
    run: Run | None = getattr(args, "_run", None)
    if run is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    started()  # Ctrl-C: quiet status 130 until here (pyrtu._startup), the command's from now
    try:
        code = run(args)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into head, less, ...
        silence_stdout()
        return EXIT_OK
    try:  # a command that stopped quietly on a closed pipe may leave output buffered
        sys.stdout.flush()
    except BrokenPipeError:
        silence_stdout()
    return code


def _logging(verbose: int) -> None:
    """The commands report their errors themselves: the library's log is shown
    only when asked (-v: info, -vv: debug, with the frames)."""
    level = {0: logging.CRITICAL, 1: logging.INFO}.get(verbose, logging.DEBUG)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(relativeCreated)9.1f ms %(name)s: %(message)s"))
    logger = logging.getLogger("pyrtu")
    logger.handlers[:] = [handler]
    logger.setLevel(level)
    logger.propagate = False


def _register_builtins() -> None:
    from pyrtu.cli import bench, demo, info, io, poll, scan, simulate, sniff, vbus

    for module in (io, poll, scan, info, sniff, simulate, vbus, demo, bench):
        for spec in module.COMMANDS:
            register(*spec)
    from pyrtu.cli import gateway

    for spec in gateway.COMMANDS:
        register(*spec)
    from pyrtu.cli import bridge

    for spec in bridge.COMMANDS:
        register(*spec)
    from pyrtu.cli import template

    for spec in template.COMMANDS:
        register(*spec)


_register_builtins()

#: the name before issue 28's one name per concept (a drive's command word is a Command)
__getattr__ = renamed(__name__, {"Command": ("pyrtu.cli.app", "Subcommand")})
