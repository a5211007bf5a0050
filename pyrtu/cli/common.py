"""What the ``pyrtu`` subcommands share: the serial options, the exit codes, error
reporting, ``--json`` output and a stop flag for SIGINT/SIGTERM.

Exit codes (`EXIT_CODES`; ``pyrtu --help`` lists them):

===  ===============  ==============================================================
 0   ok               the command did what was asked
 1   failure          anything else went wrong (an internal error, the bus hub failed)
 2   usage            bad arguments or values (argparse's own code, kept for all)
 3   port             a port or file cannot be opened or used: missing, busy, a
                      refused format (parity E/O on a pseudo-terminal), unplugged,
                      an unreadable capture file
 4   no response      nothing valid came back within ``--timeout`` (scan: no slave found)
 5   exception        the slave answered with a Modbus exception response
 6   frame            an answer came but cannot be the answer: bad CRC/LRC, another
                      slave or function, malformed data, echo mismatch
130  interrupted      Ctrl-C during a one-shot command (read, write, info, scan), or
                      while any command starts (`pyrtu._startup`: quietly)
===  ===============  ==============================================================

``poll``, ``sniff``, ``simulate``, ``vbus`` and ``demo`` run until their end
(``--count``, ``--duration``) or SIGINT/SIGTERM, which is a normal stop (0).
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import re
import sys
from collections.abc import Callable, Mapping
from typing import IO, TYPE_CHECKING, Any, NamedTuple, NoReturn

from pyrtu.cli._signals import SignalStop, stop_on_signals, stop_when_stdout_closes
from pyrtu.core import timing
from pyrtu.core.line import LINE_DEFAULTS, split_field_error

try:  # POSIX: pyserial lets termios.error through when a port refuses a format
    import termios

    _TERMIOS_ERRORS: tuple[type[Exception], ...] = (termios.error,)
except ImportError:  # no termios (Windows): pyserial raises its own errors there
    _TERMIOS_ERRORS = ()

if TYPE_CHECKING:
    from pyrtu.core.line import LineConfig
    from pyrtu.drivers.master import Master
    from pyrtu.pdu.errors import PortError

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_PORT = 3
EXIT_NO_RESPONSE = 4
EXIT_EXCEPTION = 5
EXIT_FRAME = 6
EXIT_INTERRUPTED = 130

#: exit code -> (kind, meaning); the kind is the ``error`` field of ``--json`` output
EXIT_CODES: Mapping[int, tuple[str, str]] = {
    EXIT_OK: ("ok", "success"),
    EXIT_FAILURE: ("failure", "another failure (internal error, bus hub failed)"),
    EXIT_USAGE: ("usage", "bad arguments or values"),
    EXIT_PORT: ("port", "port or file error: missing, busy, refused format, unplugged"),
    EXIT_NO_RESPONSE: ("no_response", "no response within the timeout (scan: no slave)"),
    EXIT_EXCEPTION: ("exception", "the slave answered with an exception response"),
    EXIT_FRAME: ("frame", "a bad answer: CRC/LRC, wrong slave/function, malformed"),
    EXIT_INTERRUPTED: ("interrupted", "interrupted (Ctrl-C): a one-shot command, any start-up"),
}

Configure = Callable[[argparse.ArgumentParser], None]
Run = Callable[[argparse.Namespace], int]


class CommandSpec(NamedTuple):
    """A subcommand as a module declares it; `pyrtu.cli` registers it."""

    name: str
    help: str
    configure: Configure
    run: Run
    description: str | None = None


class JsonErrorParser(argparse.ArgumentParser):
    """argparse with ``--json`` honoured for usage errors too: the error object goes
    to stdout (the usual message and exit code 2 stay)."""

    json_errors = False

    def error(self, message: str) -> NoReturn:
        if JsonErrorParser.json_errors:
            command = self.prog.removeprefix("pyrtu").strip() or "pyrtu"
            emit(
                {
                    "ok": False,
                    "error": "usage",
                    "exit_code": EXIT_USAGE,
                    "message": f"{command}: {message}",
                }
            )
        super().error(message)


def exit_code_table() -> str:
    """The exit codes, for ``--help`` epilogs."""
    lines = ["exit codes:"]
    for code, (kind, meaning) in EXIT_CODES.items():
        lines.append(f"  {code:>3}  {kind:<12} {meaning}")
    return "\n".join(lines)


# -- argument types -------------------------------------------------------------------

#: the longest time any option takes (about 31 years): beyond, microseconds overflow
MAX_SECONDS = 1e9
#: the baud rates every layer accepts (`pyrtu.core.timing`: the range termios names)
MAX_BAUDRATE = timing.MAX_BAUDRATE
MIN_BAUDRATE = timing.MIN_BAUDRATE

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(s|ms|us|µs)?\s*$")


def seconds(text: str) -> float:
    """``"0.5"``, ``"500ms"``, ``"1750us"`` -> seconds (argparse type)."""
    m = _DURATION.match(text)
    if not m:
        raise argparse.ArgumentTypeError(
            f"expected seconds (e.g. 0.5, 500ms, 1750us), not {text!r}"
        )
    value = (
        float(m.group(1)) * {None: 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}[m.group(2)]
    )
    if not math.isfinite(value) or value > MAX_SECONDS:
        raise argparse.ArgumentTypeError(
            f"expected a time of at most {MAX_SECONDS:g} s, not {text!r}"
        )
    return value


def positive_seconds(text: str) -> float:
    value = seconds(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive time, not {text!r}")
    return value


def bounded_int(low: int, high: int | None, what: str = "an integer") -> Callable[[str], int]:
    """An argparse type: a decimal (or 0x hex) integer within [low, high]."""

    def convert(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, not {text!r}") from None
        if value < low or (high is not None and value > high):
            span = f"{low}..{high}" if high is not None else f"{low} or more"
            raise argparse.ArgumentTypeError(f"expected {what} {span}, not {text!r}")
        return value

    convert.__name__ = what.replace(" ", "_")
    return convert


def line_value(name: str, convert: Callable[[str], Any], check: Callable[[Any], Any]) -> Any:
    """An argparse type for a line parameter: ``convert`` the text, then the check
    `pyrtu.LineConfig` makes, with its words (``argument -b/--baudrate: must be an
    integer 50..4000000, not 100000000``, as the TOML loader says after its
    ``file:line: bus[0]: baudrate:`` and the API after ``baudrate``)."""

    def parse(text: str) -> Any:
        try:
            value = convert(text.strip())
        except ValueError:
            value = text
        try:
            return check(value)
        except ValueError as exc:  # ArgumentTypeError (a TypeError) included
            raise argparse.ArgumentTypeError(split_field_error(exc, (name,))[1]) from None

    parse.__name__ = name
    return parse


def _number(text: str) -> int | float:
    value = float(text)
    return int(value) if value.is_integer() and "." not in text else value


#: ``--baudrate``, ``--parity``, ``--stopbits``, ``--bytesize``: LineConfig's checks
baudrate = line_value("baudrate", lambda t: int(t, 10), timing.check_baudrate)
parity = line_value("parity", str, timing.check_parity)
stopbits = line_value("stopbits", _number, timing.check_stopbits)
bytesize = line_value("bytesize", lambda t: int(t, 10), timing.check_bytesize)
mode = line_value("mode", str.lower, timing.check_mode)
timing_rule = line_value("timing", str.lower, timing.check_timing)
#: ``--count``: 1 or more (there is no "0 = unlimited": leave the option out)
count = bounded_int(1, None, "a count")


def finite_float(low: float, high: float, what: str) -> Callable[[str], float]:
    """An argparse type: a finite number within [low, high] (no nan, no inf)."""

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, not {text!r}") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"expected {what} {low:g}..{high:g}, not {text!r}")
        return value

    convert.__name__ = what.replace(" ", "_")
    return convert


class HexInt(int):
    """An integer the user wrote in hexadecimal (shown back in hexadecimal)."""

    def __repr__(self) -> str:
        return f"0x{int(self):04X}"


def integer(text: str) -> int:
    """Decimal, ``0x`` hex, ``0o``/``0b`` (argparse type); hex gives a `HexInt`."""
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, not {text!r}") from None
    return HexInt(value) if text.strip().lower().startswith("0x") else value


def register_address(text: str) -> int:
    """A register or bit address 0..65535 (decimal or 0x hex; argparse type)."""
    value = integer(text)
    if not 0 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"an address is 0..65535 (0xFFFF), not {text!r}")
    return value


def object_id(text: str) -> int:
    """A device identification object id 0..255 (argparse type)."""
    value = integer(text)
    if not 0 <= value <= 0xFF:
        raise argparse.ArgumentTypeError(f"an object id is 0..255 (0xFF), not {text!r}")
    return value


def show_address(address: int, like: int) -> str:
    """``address`` in the base the user wrote ``like`` in."""
    return f"0x{address:04X}" if isinstance(like, HexInt) else str(address)


def slave_address(text: str) -> int:
    value = integer(text)
    if not 0 <= value <= 247:
        raise argparse.ArgumentTypeError(f"a slave address is 1..247 (0: broadcast), not {value}")
    return value


def add_slave_option(p: argparse.ArgumentParser, help: str = "slave address (default 1)") -> None:
    """``-a/--slave`` (0..247, default 1), shared by the commands that address one slave."""
    p.add_argument("-a", "--slave", type=slave_address, default=1, metavar="N", help=help)


# -- the serial options -----------------------------------------------------------------


def add_serial_options(
    p: argparse.ArgumentParser,
    *,
    timeout: float | None = 1.0,
    parity_default: str = "E",
    timeout_by_port: str | None = None,
) -> None:
    """``--baudrate --parity --stopbits --bytesize --timeout --retries --mode --t35
    --timing --echo``: the `pyrtu.Master` keywords (``timeout=None``: no timeout and
    retries options, for the commands that only listen or serve; ``timeout_by_port``:
    ``--timeout`` defaults to None, the command picks it by the port, as this text
    says in the help)."""
    g = p.add_argument_group("serial line (the keywords of pyrtu.Master)")
    g.add_argument(
        "-b",
        "--baudrate",
        type=baudrate,
        default=19200,
        metavar="BAUD",
        help=f"(default 19200; {MIN_BAUDRATE}..{MAX_BAUDRATE})",
    )
    g.add_argument(
        "-P",
        "--parity",
        type=parity,
        default=parity_default,
        metavar="N|E|O",
        help=f"(default {parity_default}; also M, S; pseudo-terminals and the virtual bus need N)",
    )
    g.add_argument("--stopbits", type=stopbits, default=1, metavar="1|1.5|2", help="(default 1)")
    g.add_argument("--bytesize", type=bytesize, default=8, metavar="7|8", help="(default 8)")
    g.add_argument("--mode", type=mode, default="rtu", metavar="rtu|ascii", help="(default rtu)")
    add_seconds_option(
        g,
        "--t35",
        default=None,
        help="inter-frame silence (default: 3.5 characters, 1.75 ms above 19200 baud; 0: off)",
        parse=seconds,
    )
    g.add_argument(
        "--timing",
        type=timing_rule,
        default="modbus",
        metavar="modbus|weg",
        help="timing rule above 19200 baud (default modbus)",
    )
    add_exclusive_option(g)
    if timeout is not None:
        add_seconds_option(
            g,
            "-o",
            "--timeout",
            default=None if timeout_by_port else timeout,
            help=f"response timeout (default {timeout_by_port or f'{timeout:g} s'}; "
            "500ms works too)",
        )
        g.add_argument(
            "--retries",
            type=bounded_int(0, 100, "a number of retries"),
            default=0,
            metavar="N",
            help="repeat a failed transaction (0..100)",
        )
        g.add_argument(
            "--echo", action="store_true", help="the adapter echoes what it sends (read it back)"
        )


def add_exclusive_option(g: Any) -> None:
    """``--no-exclusive``: open the port without the exclusive lock (pyrtu.open_port)."""
    g.add_argument(
        "--no-exclusive",
        dest="exclusive",
        action="store_false",
        help="share the port with other programs (default: opened exclusively; "
        "a port another program holds is an error, exit 3)",
    )


def add_seconds_option(
    g: Any,
    *flags: str,
    default: float | None,
    help: str,
    parse: Callable[[str], float] = positive_seconds,
) -> None:
    """An option that takes a time, ``SECONDS`` (``1.5``, ``500ms``: the units `seconds`
    reads), read by ``parse`` (default: more than 0)."""
    g.add_argument(*flags, type=parse, default=default, metavar="SECONDS", help=help)


def add_duration_option(g: Any, help: str = "stop after this time") -> None:
    """``-d/--duration SECONDS`` (default None: until a signal), shared by the commands
    that run until stopped."""
    add_seconds_option(g, "-d", "--duration", default=None, help=help)


def add_count_option(g: Any, help: str = "stop after N (1 or more)", dest: str = "count") -> None:
    """``-n/--count N`` (default None: no limit), shared by the commands that can stop
    after N of what they do."""
    g.add_argument("-n", "--count", dest=dest, type=count, default=None, metavar="N", help=help)


def add_json_option(p: argparse.ArgumentParser, what: str = "one JSON document") -> None:
    p.add_argument("--json", action="store_true", help=f"output for scripts: {what} on stdout")


def serial_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The byte format of the serial options."""
    return {
        "baudrate": args.baudrate,
        "parity": args.parity,
        "stopbits": _stopbits(args.stopbits),
        "bytesize": args.bytesize,
    }


def _stopbits(value: float) -> float:
    return int(value) if value == int(value) else value


def framing_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Serial format plus the framer's timing options."""
    out = serial_kwargs(args)
    out.update(timing=args.timing, t35=args.t35)
    return out


def line_config(args: argparse.Namespace, **overrides: Any) -> LineConfig:
    """The `LineConfig` of the serial and timing options (ValueError names the field)."""
    from pyrtu.core.line import LineConfig

    kwargs: dict[str, Any] = serial_kwargs(args)
    kwargs.update(mode=args.mode, timing=args.timing, t35=args.t35)
    kwargs.update(overrides)
    return LineConfig(**kwargs)


def describe_format(args: argparse.Namespace) -> str:
    stop = {1.0: "1", 1.5: "1.5", 2.0: "2"}[float(args.stopbits)]
    return f"{args.baudrate} baud {args.bytesize}{args.parity}{stop}"


def open_master(args: argparse.Namespace, **overrides: Any) -> Master:
    """A `pyrtu.Master` on ``args.port`` with the serial options."""
    from pyrtu.drivers.master import Master

    line_fields = {k: overrides.pop(k) for k in list(overrides) if k in _LINE_FIELDS}
    kwargs: dict[str, Any] = dict(
        timeout=args.timeout, retries=args.retries, echo=args.echo, exclusive=args.exclusive
    )
    kwargs.update(overrides)
    return Master(args.port, line=line_config(args, **line_fields), **kwargs)


_LINE_FIELDS = frozenset(LINE_DEFAULTS)  # the LineConfig fields


# -- errors -------------------------------------------------------------------------------


def classify(exc: BaseException) -> int:
    """The exit code for an exception."""
    from pyrtu.pdu.errors import (
        ExceptionResponseError,
        FrameError,
        ModbusError,
        NoResponseError,
        PortError,
    )
    from pyrtu.vbus.capture import CaptureError

    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(exc, PortError | CaptureError):
        return EXIT_PORT
    if isinstance(exc, NoResponseError):
        return EXIT_NO_RESPONSE
    if isinstance(exc, ExceptionResponseError):
        return EXIT_EXCEPTION
    if isinstance(exc, FrameError):
        return EXIT_FRAME
    if isinstance(exc, ModbusError):
        return EXIT_FAILURE
    if isinstance(exc, OSError):
        return EXIT_PORT
    if isinstance(exc, ValueError | OverflowError):
        return EXIT_USAGE
    return EXIT_FAILURE


def kind_of(code: int) -> str:
    return EXIT_CODES.get(code, ("failure", ""))[0]


def error_document(exc: BaseException, code: int) -> dict[str, Any]:
    """The ``--json`` form of an error."""
    from pyrtu.pdu.errors import ExceptionResponseError

    doc: dict[str, Any] = {
        "ok": False,
        "error": kind_of(code),
        "exit_code": code,
        "message": message_of(exc),
    }
    if isinstance(exc, ExceptionResponseError):
        doc.update(
            slave=exc.slave,
            function=exc.function,
            exception_code=exc.code,
            exception_name=exc.name,
        )
    return doc


def message_of(exc: BaseException) -> str:
    if isinstance(exc, KeyboardInterrupt):
        return "stopped by SIGINT (Ctrl-C)"
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc) or type(exc).__name__


#: what people read before the message, by kind
LABELS = {
    "failure": "error",
    "usage": "error",
    "port": "port error",
    "no_response": "no response",
    "exception": "exception response",
    "frame": "frame error",
    "interrupted": "interrupted",
}


def port_error(exc: Exception, port: str, fmt: str) -> PortError:
    """pyserial lets the ``termios.error`` of a refused format through: as a PortError."""
    from pyrtu.pdu.errors import PortError

    code = exc.args[0] if exc.args and isinstance(exc.args[0], int) else None
    text = exc.args[1] if len(exc.args) > 1 else str(exc)
    hint = ""
    if code == errno.EINVAL:
        hint = " (pseudo-terminals and the virtual bus carry no parity: use --parity N)"
    return PortError(port, f"the port refused the format {fmt}: {text}{hint}")


#: the library's advice in its own terms -> the command line's
_CLI_TERMS = (("use parity='N'", "use --parity N"),)
#: what a command with ``--no-exclusive`` (`add_exclusive_option`) advises for a busy port
BUSY_ADVICE = "use --no-exclusive to share it"


def in_cli_terms(exc: BaseException, shares: bool = True) -> BaseException:
    """A PortError whose advice names Python keywords, reworded with the CLI flags.
    A busy port (`pyrtu.pdu.errors.PortBusyError`): `BUSY_ADVICE` when the command
    ``shares`` ports on request (has ``--no-exclusive``), else no advice."""
    from pyrtu.pdu.errors import PortBusyError, PortError

    if isinstance(exc, PortBusyError):
        return exc.with_advice(BUSY_ADVICE if shares else None)
    if not isinstance(exc, PortError):
        return exc
    text = str(exc)
    for python, cli in _CLI_TERMS:
        text = text.replace(python, cli)
    if text == str(exc):
        return exc
    out = PortError(exc.port, text.removeprefix(f"{exc.port}: "))
    out.__cause__ = exc.__cause__
    return out


def silence_stdout() -> None:
    """The reader of stdout went away (``| head``): point stdout at /dev/null, so that
    what is still buffered, flushed when Python exits, does not fail there too (a
    "BrokenPipeError ... Exception ignored" and exit status 120)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


def report_error(
    command: str, exc: BaseException, json_output: bool, out: IO[str] | None = None
) -> int:
    """Print the error for people (stderr) and, with ``--json``, as a document on
    stdout; returns the exit code."""
    code = classify(exc)
    label = LABELS.get(kind_of(code), "error")
    print(f"pyrtu {command}: {label}: {message_of(exc)}", file=sys.stderr)
    if json_output:
        emit(error_document(exc, code), out)
    return code


def guarded(command: str, run: Run) -> Run:
    """``run`` with its errors turned into messages and exit codes."""

    def wrapper(args: argparse.Namespace) -> int:
        try:
            return run(args)
        except (Exception, KeyboardInterrupt) as exc:
            from pyrtu.pdu.errors import ModbusError

            error: BaseException = exc
            if isinstance(exc, BrokenPipeError):
                raise  # the reader went away (| head): pyrtu.cli.main ends quietly
            if isinstance(exc, _TERMIOS_ERRORS):
                fmt = describe_format(args) if hasattr(args, "baudrate") else "asked"
                error = port_error(exc, str(getattr(args, "port", "?")), fmt)
            elif not isinstance(
                exc, ModbusError | OSError | ValueError | OverflowError | KeyboardInterrupt
            ):
                raise
            error = in_cli_terms(error, shares=hasattr(args, "exclusive"))
            return report_error(command, error, bool(getattr(args, "json", False)))

    wrapper.__name__ = getattr(run, "__name__", "run")
    wrapper.__doc__ = run.__doc__
    return wrapper


# -- output ---------------------------------------------------------------------------------


def jsonable(value: Any) -> Any:
    """Floats that JSON cannot hold (NaN, infinities) as strings; bytes as text."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, bytes):
        return value.decode("latin-1")
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    return value


def emit(doc: Mapping[str, Any], out: IO[str] | None = None) -> None:
    """One JSON document on one line (stdout), flushed."""
    stream = out if out is not None else sys.stdout
    stream.write(json.dumps(jsonable(dict(doc)), allow_nan=False) + "\n")
    stream.flush()


__all__ = [
    "EXIT_CODES",
    "EXIT_EXCEPTION",
    "EXIT_FAILURE",
    "EXIT_FRAME",
    "EXIT_INTERRUPTED",
    "EXIT_NO_RESPONSE",
    "EXIT_OK",
    "EXIT_PORT",
    "EXIT_USAGE",
    "CommandSpec",
    "JsonErrorParser",
    "SignalStop",
    "add_json_option",
    "add_serial_options",
    "classify",
    "emit",
    "error_document",
    "exit_code_table",
    "guarded",
    "open_master",
    "report_error",
    "seconds",
    "serial_kwargs",
    "stop_on_signals",
    "stop_when_stdout_closes",
]
