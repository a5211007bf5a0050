"""``pyrtu demo``: the README's main command, without hardware.

A virtual RS-485 bus (`pyrtu.vbus`, in this process, 19200 baud; the drops are
pseudo-terminals, opened 8N1) with four simulated drives, one per manufacturer:

====  =====  ==============================  ======================================
drop  slave  drive                           identified by
====  =====  ==============================  ======================================
1     1      WEG CFW701                      FC 43 (vendor, product, revision)
2     2      WEG CFW100                      FC 43
3     3      Bonfiglioli Vectron ACU         its profile (no FC 43: parameters)
4     5      CV100/FV100                     its profile (no FC 43: 0x3302-0x3304)
====  =====  ==============================  ======================================

A `pyrtu.Master` on drop 0 identifies them, starts the CFW701 (control word P682)
with a 30 Hz reference (P683 on the 13-bit scale), then reads every drive's
frequency and status word over and over: a live view redrawn in place on a
terminal (`pyrtu.cli.live_view`: cut to the terminal's size, whatever it is),
plain lines otherwise (one block per ``--interval``).  It ends by
itself after ``--duration`` seconds (default 12) and exits 0; 1 if the bus or
the master could not be set up.  The CFW701's acceleration time P100 is short
(``--accel``, default 10 s from 0 to its maximum 66 Hz: 30 Hz in 4.5 s), so
the ramp is seen within the run.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from pyrtu.cli.common import (
    EXIT_FAILURE,
    EXIT_OK,
    MAX_BAUDRATE,
    CommandSpec,
    add_seconds_option,
    baudrate,
    message_of,
    stop_on_signals,
)
from pyrtu.cli.live_view import LiveView

TARGET_HZ = 30.0
BAR_HZ = 40.0  # full scale of the live view's bars
WEG_MAX_HZ = 66.0  # P134 of the simulated CFW701 (the ramp times run from 0 to it)


@dataclass
class Drive:
    """One simulated drive and what the master last saw of it."""

    device: str
    address: int
    title: str
    sim: Any = None
    profile: Any = None
    ident: str = ""
    ident_how: str = ""
    hz: float | None = None
    word_name: str = ""
    word: int | None = None
    status: str = ""
    error: str | None = None
    errors: int = 0


@dataclass
class Stats:
    latencies: list[float] = field(default_factory=list)
    transactions: int = 0
    errors: int = 0

    def percentile(self, q: float) -> float | None:
        if not self.latencies:
            return None
        lat = sorted(self.latencies)
        return lat[min(len(lat) - 1, max(0, math.ceil(len(lat) * q / 100) - 1))]


DRIVES = (
    ("cfw701", 1, "WEG CFW701"),
    ("cfw100", 2, "WEG CFW100"),
    ("acu", 3, "Bonfiglioli ACU"),
    ("cv100", 5, "CV100"),
)


def configure(p: argparse.ArgumentParser) -> None:
    add_seconds_option(
        p,
        "-d",
        "--duration",
        default=12.0,
        help="length of the run (default 12 s)",
    )
    add_seconds_option(
        p,
        "--accel",
        default=10.0,
        help="the CFW701's acceleration time P100, 0 to 66 Hz (default 10 s)",
    )
    p.add_argument(
        "-b",
        "--baudrate",
        type=baudrate,
        default=19200,
        metavar="BAUD",
        help=f"(default 19200; at most {MAX_BAUDRATE})",
    )
    add_seconds_option(
        p,
        "-i",
        "--interval",
        default=1.0,
        help="time between blocks of plain lines (default 1 s)",
    )
    p.add_argument(
        "--plain", action="store_true", help="plain lines even when the output is a terminal"
    )


def pyrtu_command() -> str:
    """How to run ``pyrtu`` from here: ``pyrtu`` when that is this installation on
    PATH, else the script beside this interpreter (``.venv/bin/pyrtu`` after ``make
    demo``, whose virtual environment is not activated), else ``python -m pyrtu``."""
    here = os.path.join(os.path.dirname(sys.executable), "pyrtu")
    found = shutil.which("pyrtu")
    if found is not None and os.path.realpath(found) == os.path.realpath(here):
        return "pyrtu"
    if os.access(here, os.X_OK):
        rel = os.path.relpath(here)
        return rel if not rel.startswith("..") else here
    return f"{sys.executable} -m pyrtu"


def response_timeout(char_time: float) -> float:
    """The master's timeout: 0.3 s of slack plus the wire time of the longest
    transaction (a request and a 256-byte answer, [SL] 2.5.1), so that slow lines
    (1200 baud and below) work as well as fast ones."""
    return 0.3 + (8 + 256 + 8) * char_time


def run(args: argparse.Namespace) -> int:
    from pyrtu.pdu.errors import ModbusError

    try:
        return Demo(args).run()
    except BrokenPipeError:
        raise  # the reader went away (| head): pyrtu.cli.main ends quietly, as for all
    except (ModbusError, OSError, RuntimeError) as exc:
        print(f"pyrtu demo: failed: {message_of(exc)}", file=sys.stderr)
        return EXIT_FAILURE


class Demo:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.drives = [Drive(d, a, t) for d, a, t in DRIVES]
        self.stats = Stats()
        term = os.environ.get("TERM", "")
        self.live = sys.stdout.isatty() and not args.plain and term != "dumb"
        self.out = sys.stdout
        self.view = LiveView(self.out)  # fits each frame to the terminal as it is now
        self.t0 = 0.0
        self.started: float | None = None  # when the start command went out
        self.reached: float | None = None  # when the CFW701 reached the target
        self.last_block = 0.0

    # -- set-up ---------------------------------------------------------------------------

    def _simulators(self) -> None:
        from pyrtu.devices import simulator, weg

        for d in self.drives:
            state = {"state": "stopped"} if d.device in ("cfw701", "cfw100", "cv100") else {}
            d.sim = simulator(d.device, **state)
        cfw701 = self.drives[0].sim
        accel = max(1, round(self.args.accel * 10))  # P100/P101 in 0.1 s
        cfw701.set(weg.P_ACCEL_TIME, accel)
        cfw701.set(weg.P_DECEL_TIME, accel)

    def run(self) -> int:
        from pyrtu._version import __version__
        from pyrtu.core._backend import active
        from pyrtu.devices import PROFILES
        from pyrtu.drivers.master import Master
        from pyrtu.vbus import VirtualBus

        args = self.args
        self._simulators()
        baud = args.baudrate
        self.say(
            f"pyrtu {__version__} demo (backend {active.BACKEND}): a virtual RS-485 bus, "
            f"{baud} baud 8N1, a master and {len(self.drives)} simulated drives; no hardware"
        )
        with VirtualBus(1 + len(self.drives), baudrate=baud, parity="N") as bus:
            try:
                self.say(f"  {os.path.dirname(bus.paths[0])}/")
                self.say("    drop0  the master")
                for drop, d in enumerate(self.drives, start=1):
                    d.sim.serve(bus.paths[drop], d.address, baudrate=baud, parity="N")
                    self.say(f"    drop{drop}  {d.title:<16} slave address {d.address}")
                timeout = response_timeout(bus.char_time)
                with Master(bus.paths[0], baud, parity="N", timeout=timeout, retries=2) as master:
                    for d in self.drives:
                        d.profile = PROFILES[d.device](master, d.address)
                    self._identify(master)
                    self._start()
                    self._watch()
                    self.stats.transactions = master.counters["requests"]
            finally:
                for d in self.drives:
                    if d.sim is not None:
                        d.sim.close()
        self._summary()
        return EXIT_OK

    def _identify(self, master: Any) -> None:
        from pyrtu.pdu.errors import ExceptionResponseError

        self.say("identifying the drives (FC 43 where the drive has it, else its profile):")
        for d in self.drives:
            try:
                objects = master.read_device_identification(d.address)
                d.ident = " ".join(v.decode("ascii", "replace") for v in objects.values())
                d.ident_how = "FC 43"
            except ExceptionResponseError as exc:
                if exc.code != 1:
                    raise
                found = d.profile.identify()
                d.ident = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in found.items())
                d.ident_how = "profile; FC 43 answered exception 1"
            self.say(f"  slave {d.address}: {d.ident}  ({d.ident_how})")

    def _start(self) -> None:
        from pyrtu.devices import weg

        drive = self.drives[0].profile
        drive.start()
        drive.set_speed_hz(TARGET_HZ)
        self.started = time.monotonic()
        control = drive.control()
        ref = drive.read(weg.P_REFERENCE)
        active = [n for n in ("run", "enable", "forward", "remote") if getattr(control, n)]
        self.say(
            f"slave 1 (CFW701): start: P682 = 0x{control.encode():04X} ({', '.join(active)}); "
            f"reference {TARGET_HZ:g} Hz: P683 = {ref} "
            f"({ref}/8192 of P403 = {drive.rated_hz():g} Hz)"
        )

    # -- the run --------------------------------------------------------------------------

    def _watch(self) -> None:
        args = self.args
        self.t0 = time.monotonic()
        end = self.t0 + args.duration
        next_block = self.t0 + args.interval
        if not self.live:
            self.say("time     slave drive            frequency  status word")
        with stop_on_signals() as stop:
            try:
                if self.live:
                    self.out.write("\x1b[?25l")  # hide the cursor
                while not stop.is_set() and time.monotonic() < end:
                    self._poll_all()
                    now = time.monotonic()
                    if self.live:
                        self._draw(now)
                    elif now >= next_block:
                        self._block(now)
                        next_block += args.interval
                now = time.monotonic()
                if self.live:
                    self._draw(now)
                elif now - self.last_block > args.interval / 2:
                    self._block(now)
            finally:
                if self.live:
                    self.view.close()
                    self.out.write("\x1b[?25h")
                    self.out.flush()

    def _poll_all(self) -> None:
        from pyrtu.pdu.errors import ModbusError, PortError

        for d in self.drives:
            t = time.monotonic()
            try:
                status = d.profile.status()
                hz = d.profile.frequency_hz()
            except PortError:
                raise
            except ModbusError as exc:
                d.error = message_of(exc)
                d.errors += 1
                self.stats.errors += 1
                continue
            self.stats.latencies.append(time.monotonic() - t)
            d.error = None
            d.hz = hz
            d.status = status.describe()
            if d.device.startswith("cfw"):
                d.word_name, d.word = "P680", status.word
            elif d.device == "cv100":
                d.word_name, d.word = "SW1", status.word1.word
            else:
                d.word_name, d.word = "411", status.word
            if d is self.drives[0] and self.reached is None and abs(hz - TARGET_HZ) <= 0.1:
                self.reached = time.monotonic()

    def _row(self, d: Drive, bar: bool) -> str:
        hz = "   --   " if d.hz is None else f"{d.hz:6.2f} Hz"
        gauge = ""
        if bar:
            filled = 0 if d.hz is None else round(20 * min(abs(d.hz), BAR_HZ) / BAR_HZ)
            gauge = " [" + "#" * filled + "." * (20 - filled) + "]"
        word = "" if d.word is None else f"{d.word_name} 0x{d.word:04X} "
        state = f"no answer: {d.error}" if d.error else f"{word}{d.status}"
        return f"{d.address:5d} {d.title:<16} {hz}{gauge}  {state}"

    def _block(self, now: float) -> None:
        self.last_block = now
        for i, d in enumerate(self.drives):
            head = f"{now - self.t0:5.1f} s " if i == 0 else " " * 8
            self.say(head + self._row(d, False))

    def _draw(self, now: float) -> None:
        lines = [
            f"\x1b[1mt = {now - self.t0:4.1f} s of {self.args.duration:g} s\x1b[0m   "
            f"CFW701 reference {TARGET_HZ:g} Hz",
            f"slave drive            frequency  (0-{BAR_HZ:g} Hz)                status word",
        ]
        lines += [self._row(d, True) for d in self.drives]
        p50 = self.stats.percentile(50)
        lines.append(
            f"bus: {len(self.stats.latencies)} reads, {self.stats.errors} errors"
            + ("" if p50 is None else f", latency p50 {p50 * 1e3:.1f} ms")
        )
        self.view.draw(lines)

    def _summary(self) -> None:
        s = self.stats
        p50, p99 = s.percentile(50), s.percentile(99)
        lat = ""
        if p50 is not None and p99 is not None:
            lat = (
                f"; a drive's status and frequency in p50 {p50 * 1e3:.1f} ms, "
                f"p99 {p99 * 1e3:.1f} ms"
            )
        rate = s.transactions / self.args.duration
        self.say(f"bus: {s.transactions} transactions ({rate:.0f}/s), {s.errors} errors{lat}")
        cfw = self.drives[0]
        if self.reached is not None and self.started is not None:
            self.say(
                f"the CFW701 reached {TARGET_HZ:g} Hz {self.reached - self.started:.1f} s after "
                f"the start (P100 = {self.args.accel:g} s for 0-{WEG_MAX_HZ:g} Hz); "
                f"now {cfw.hz:.2f} Hz, {cfw.status}"
            )
        else:
            now = "--" if cfw.hz is None else f"{cfw.hz:.2f}"
            self.say(f"the CFW701 is at {now} Hz: ramping to {TARGET_HZ:g} Hz when the run ended")
        print(
            f"next: {pyrtu_command()} --help; the same bus by hand: docs/cli.md, "
            '"A session without hardware"',
            file=sys.stderr,
        )

    def say(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()


COMMANDS = (
    CommandSpec(
        "demo",
        "simulated drives of each manufacturer on a virtual bus: identify, start, ramp",
        configure,
        run,
        (__doc__ or "").strip(),
    ),
)
