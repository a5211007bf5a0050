"""``pyrtu poll``: the same read again and again, with live statistics.

Every ``--interval`` a report: transactions per second, latency p50/p99 (the time
of a whole transaction, from the start of the inter-frame silence to the last byte
of the answer), errors by kind, and the latest values.  On a terminal the report
line is redrawn in place; otherwise one line per report; ``--json`` gives one JSON
line per report and a last one with ``"final": true`` for the whole run.

Stops after ``--count`` transactions, after ``--duration``, or on SIGINT/SIGTERM.
Exit status: 0 when every transaction succeeded, otherwise the code of the most
frequent kind of error (4 no response, 5 exception, 6 frame); 3 when the port
fails (the poll stops).

``pyrtu poll --config points.toml [--duration S] [--json]`` is the poller: it polls
every point of a TOML file (``[[bus]]``, ``[[device]]``, ``[[point]]`` tables; see
docs/POLLER.md) on all its buses at once, with a live table or JSON lines; its exit
status says what came in (3 a port never worked or is down, 4 a slave offline or a
point never read, 5 a point dropped): ``pyrtu poll --config FILE --help``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from pyrtu.cli.common import (
    EXIT_EXCEPTION,
    EXIT_FRAME,
    EXIT_NO_RESPONSE,
    EXIT_OK,
    EXIT_PORT,
    CommandSpec,
    add_count_option,
    add_duration_option,
    add_json_option,
    add_seconds_option,
    add_serial_options,
    emit,
    exit_code_table,
    finite_float,
    guarded,
    message_of,
    open_master,
    stop_on_signals,
)
from pyrtu.cli.io import ReadResult, add_read_arguments, check_read, is_bits, read_values, show
from pyrtu.cli.live_view import LiveView


def percentile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank percentile (``q`` in 0..100) of sorted values; None if empty."""
    if not sorted_values:
        return None
    rank = max(1, -(-len(sorted_values) * q // 100))  # ceil
    return sorted_values[int(rank) - 1]


@dataclass
class Window:
    """Statistics of a span of the run."""

    start: float
    transactions: int = 0
    ok: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    latencies: list[float] = field(default_factory=list)

    def add(self, latency: float, error: str | None) -> None:
        self.transactions += 1
        if error is None:
            self.ok += 1
            self.latencies.append(latency)
        else:
            self.errors[error] += 1

    def summary(self, now: float) -> dict[str, Any]:
        span = max(now - self.start, 1e-9)
        lat = sorted(self.latencies)
        p50, p99 = percentile(lat, 50), percentile(lat, 99)
        return {
            "seconds": round(span, 3),
            "transactions": self.transactions,
            "ok": self.ok,
            "errors": dict(self.errors),
            "per_second": round(self.transactions / span, 2),
            "latency_ms": {
                "p50": None if p50 is None else round(p50 * 1e3, 3),
                "p99": None if p99 is None else round(p99 * 1e3, 3),
                "max": round(lat[-1] * 1e3, 3) if lat else None,
            },
        }


def error_kind(exc: BaseException) -> str | None:
    """The statistics key of a failed transaction (None: not a bus error)."""
    from pyrtu.pdu.errors import ExceptionResponseError, FrameError, NoResponseError

    if isinstance(exc, NoResponseError):
        return "no_response"
    if isinstance(exc, ExceptionResponseError):
        return f"exception_{exc.code}"
    if isinstance(exc, FrameError):
        return "frame"
    return None


def exit_status(errors: Counter[str]) -> int:
    """0 without errors, else the code of the most frequent kind."""
    if not errors:
        return EXIT_OK
    kind = errors.most_common(1)[0][0]
    if kind == "no_response":
        return EXIT_NO_RESPONSE
    if kind.startswith("exception"):
        return EXIT_EXCEPTION
    return EXIT_FRAME


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f} ms"


def report_line(doc: dict[str, Any]) -> str:
    """A report for people."""
    w, total = doc["interval"], doc["total"]
    errors = total["errors"]
    err = ", ".join(f"{k} {v}" for k, v in sorted(errors.items())) if errors else "none"
    lat = w["latency_ms"]
    line = (
        f"{doc['t']:7.1f} s  {total['transactions']:6d} tx  {w['per_second']:7.1f} tx/s"
        f"  p50 {_ms(lat['p50'])}  p99 {_ms(lat['p99'])}  errors: {err}"
    )
    if doc.get("values") is not None:
        line += "  | " + doc["values_text"]
    return line


def final_line(doc: dict[str, Any]) -> str:
    total = doc["total"]
    lat = total["latency_ms"]
    errors = total["errors"]
    err = ", ".join(f"{k} {v}" for k, v in sorted(errors.items())) if errors else "none"
    return (
        f"{total['transactions']} transactions in {total['seconds']:.1f} s "
        f"({total['per_second']:.1f}/s), {total['ok']} ok; latency p50 {_ms(lat['p50'])}, "
        f"p99 {_ms(lat['p99'])}, max {_ms(lat['max'])}; errors: {err}"
    )


def _values_text(result: ReadResult) -> str:
    kind = "bit" if is_bits(result.table) else result.kind
    text_kind = kind in ("string", "string1")
    parts = [
        f"[{a}] {show(v, kind) if text_kind else show(v, kind).split(' ')[0]}"
        for a, v in zip(result.addresses(), result.values, strict=True)
    ]
    text = " ".join(parts[:8])
    if len(parts) > 8:
        text += f" ... ({len(parts)} values)"
    return text


def _configure(p: argparse.ArgumentParser) -> None:
    add_read_arguments(p)
    g = p.add_argument_group("polling")
    g.add_argument(
        "-r",
        "--rate",
        type=finite_float(0.0, 1e6, "a rate in Hz"),
        default=10.0,
        metavar="HZ",
        help="transactions per second (default 10; 0: back to back)",
    )
    add_count_option(g, dest="polls")
    add_duration_option(g)
    add_seconds_option(
        g,
        "-i",
        "--interval",
        default=1.0,
        help="time between reports (default 1 s)",
    )
    add_json_option(p, "one JSON line per report")
    add_serial_options(p, timeout=0.5)


def _run(args: argparse.Namespace) -> int:
    from pyrtu.pdu.errors import PortError

    check_read(args)  # before the port is opened
    period = 1.0 / args.rate if args.rate > 0 else 0.0
    live = sys.stdout.isatty() and not args.json
    view = LiveView(sys.stdout)  # the report line, cut to the terminal's width
    clock = time.monotonic
    status = EXIT_OK
    with open_master(args) as master, stop_on_signals() as stop:
        start = clock()
        total = Window(start)
        window = Window(start)
        last: ReadResult | None = None
        last_error: str | None = None
        next_report = start + args.interval
        deadline = None if args.duration is None else start + args.duration
        due = start
        reports = 0

        def report(now: float, final: bool) -> None:
            nonlocal reports
            reports += 1
            doc: dict[str, Any] = {
                "report": reports,
                "final": final,
                "t": round(now - start, 3),
                "slave": args.slave,
                "interval": window.summary(now),
                "total": total.summary(now),
                "values": None if last is None else last.json_values(),
                "addresses": None if last is None else last.addresses(),
                "last_error": last_error,
            }
            if args.json:
                emit(doc)
                return
            if final:
                view.close()
                print(final_line(doc), flush=True)
                return
            doc["values_text"] = "" if last is None else _values_text(last)
            line = report_line(doc)
            if live:
                view.draw([line])
            else:
                print(line, flush=True)

        while not stop.is_set():
            now = clock()
            if deadline is not None and now >= deadline:
                break
            if args.polls is not None and total.transactions >= args.polls:
                break
            if now >= due:
                due = max(due + period, now) if period else now
                error: str | None = None
                try:
                    last = read_values(master, args)
                except PortError as exc:
                    last_error = message_of(exc)
                    print(f"pyrtu poll: port error: {last_error}", file=sys.stderr)
                    status = EXIT_PORT
                    break
                except Exception as exc:
                    error = error_kind(exc)
                    if error is None:
                        raise
                    last_error = message_of(exc)
                latency = clock() - now
                total.add(latency, error)
                window.add(latency, error)
                now = clock()
            if now >= next_report:
                report(now, False)
                window = Window(now)
                next_report = max(next_report + args.interval, now + args.interval / 2)
            wake = min(due, next_report, deadline if deadline is not None else due)
            if wake > now:
                stop.wait(wake - now)
        report(clock(), True)
    return status or exit_status(total.errors)


COMMANDS = (
    CommandSpec(
        "poll",
        "read repeatedly with live statistics; poll --config FILE: the poller (TOML)",
        _configure,
        guarded("poll", _run),
        __doc__.strip() + "\n\n" + exit_code_table() if __doc__ else None,
    ),
)
