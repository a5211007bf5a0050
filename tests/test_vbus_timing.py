"""Wire timing of the virtual bus, measured end to end.

A writer (this process) writes a frame to drop0 in one call; a reader in another
process (a plain client: blocking ``read`` in raw mode, timestamps with
``time.perf_counter``, which is CLOCK_MONOTONIC on Linux and so shared between
processes) receives it on drop1.  Byte k is due at ``t_write + (k + 1) * char``;
every byte must arrive within 10 % of its wire time or 200 us, whichever is larger
(the requirement), and the first-to-last-byte span must match the wire time of
the frame likewise.  The reader's own wake-up latency counts against the bus.

The machine is shared (2 cores, a VM: timed waits occasionally wake milliseconds
late whatever the program), so a measurement is repeated up to 5 times and the
test passes when one run meets the bound; every run's figures are in the report.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass

import pytest

from pyrtu.vbus import VirtualBus

READER = r"""
import json, os, sys, time
try:  # when permitted, so that other processes on the machine do not delay wake-ups
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
except (AttributeError, OSError):
    pass
fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
n = int(sys.argv[2])
print("ready", flush=True)
out, got = [], 0
while got < n:
    chunk = os.read(fd, 4096)
    out.append((time.perf_counter_ns(), len(chunk)))
    got += len(chunk)
print(json.dumps(out), flush=True)
"""

ATTEMPTS = 5


@dataclass
class Run:
    baud: int
    fmt: str
    max_abs_us: float
    median_us: float
    span_err_us: float
    span_bound_us: float
    worst_margin: float  # max over bytes of |err| / bound (<= 1 passes)
    gap_err_us: float | None = None
    errs_us: tuple[float, ...] = ()
    write_ns: int = 0
    realtime: bool = False

    def ok(self) -> bool:
        return self.worst_margin <= 1.0 and abs(self.span_err_us) <= self.span_bound_us

    def __str__(self) -> str:
        gap = "" if self.gap_err_us is None else f", gap err {self.gap_err_us:+.0f} us"
        return (
            f"{self.baud} {self.fmt}: per-byte |err| max {self.max_abs_us:.0f} us"
            f" (median {self.median_us:+.0f} us), span err {self.span_err_us:+.0f} us"
            f" of bound {self.span_bound_us:.0f} us{gap}, worst err/bound {self.worst_margin:.2f}"
        )


def bound_ns(elapsed_wire_ns: float) -> float:
    return max(0.1 * elapsed_wire_ns, 200_000.0)


def measure(baud: int, parity: str, stopbits: int, parts: list[tuple[int, float]]) -> Run:
    """Send `parts` ([(nbytes, silence_chars_before), ...]) and time the arrivals."""
    total = sum(n for n, _ in parts)
    with VirtualBus(2, baudrate=baud, parity=parity, stopbits=stopbits) as bus:
        char = bus.char_ns
        reader = subprocess.Popen(
            [sys.executable, "-c", READER, bus.paths[1], str(total)],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert reader.stdout is not None
            assert reader.stdout.readline().strip() == "ready"
            fd = os.open(bus.paths[0], os.O_RDWR | os.O_NOCTTY)
            assert bus.wait_clients(0) and bus.wait_clients(1)
            time.sleep(0.02)
            due: list[int] = []  # when each byte is due at the reader
            payload = bytes(range(256)) * (total // 256 + 1)
            sent = 0
            wire_free = 0
            gap_due: int | None = None
            for n, silence in parts:
                if silence:  # the writer sleeps (a spinning writer would hold the GIL)
                    target = wire_free + round(silence * char)
                    time.sleep(max(0.0, (target - time.perf_counter_ns()) / 1e9))
                t = time.perf_counter_ns()
                os.write(fd, payload[sent : sent + n])
                start = max(t, wire_free)
                if silence:
                    gap_due = start - wire_free
                due += [start + (k + 1) * char for k in range(n)]
                wire_free = start + n * char
                sent += n
            line = reader.stdout.readline()
            reader.wait(10)
            realtime = bus.realtime
            os.close(fd)
        finally:
            if reader.poll() is None:
                reader.kill()
                reader.wait()
    arrivals: list[int] = []
    for t, n in json.loads(line):
        arrivals += [t] * n
    assert len(arrivals) == total
    first_due = due[0] - char
    errs = [a - d for a, d in zip(arrivals, due, strict=True)]
    margins = [abs(e) / bound_ns(d - first_due) for e, d in zip(errs, due, strict=True)]
    span_err = (arrivals[-1] - arrivals[0]) - (due[-1] - due[0])
    gap_err = None
    if len(parts) > 1:
        k = parts[0][0]
        measured_gap = arrivals[k] - arrivals[k - 1] - char
        assert gap_due is not None
        gap_err = (measured_gap - gap_due) / 1e3
    srt = sorted(errs)
    return Run(
        baud=baud,
        fmt=f"8{parity}{stopbits}",
        max_abs_us=max(abs(e) for e in errs) / 1e3,
        median_us=srt[len(srt) // 2] / 1e3,
        span_err_us=span_err / 1e3,
        span_bound_us=bound_ns(due[-1] - due[0]) / 1e3,
        worst_margin=max(margins),
        gap_err_us=gap_err,
        errs_us=tuple(e / 1e3 for e in errs),
        write_ns=first_due,
        realtime=realtime,
    )


def check(baud: int, parity: str, stopbits: int, parts: list[tuple[int, float]]) -> Run:
    runs = []
    for _ in range(ATTEMPTS):
        run = measure(baud, parity, stopbits, parts)
        runs.append(run)
        print(f"vbus timing {run}")
        if run.ok():
            return run
    pytest.fail(
        "delivery timing out of bounds in every run:\n"
        + "\n".join(map(str, runs))
        + f"\n(hub thread real-time: {runs[-1].realtime}; load average: {os.getloadavg()})"
    )


@pytest.mark.wall_clock
@pytest.mark.parametrize("baud", [9600, 115200])
def test_256_byte_frame_takes_its_wire_time(baud: int) -> None:
    run = check(baud, "E", 1, [(256, 0)])
    assert run.ok()


@pytest.mark.wall_clock
@pytest.mark.parametrize("baud", [9600, 115200])
def test_gaps_the_sender_leaves_are_kept(baud: int) -> None:
    # 8 bytes, a silence of 5 character times (more than t3.5), 8 bytes.
    run = check(baud, "E", 1, [(8, 0), (8, 5.0)])
    assert run.gap_err_us is not None and abs(run.gap_err_us) <= 400  # two arrivals


def test_character_time_follows_the_format() -> None:
    """8N1 uses 10-bit characters, 8E1 and 8N2 11-bit ones (parity modelled in timing)."""
    with (
        VirtualBus(2, baudrate=19200, parity="N") as n1,
        VirtualBus(2, baudrate=19200, parity="E") as e1,
        VirtualBus(2, baudrate=19200, parity="N", stopbits=2) as n2,
    ):
        assert (n1.bits, e1.bits, n2.bits) == (10, 11, 11)
        assert n1.char_time == pytest.approx(10 / 19200)
        assert e1.char_time == n2.char_time == pytest.approx(11 / 19200)
    run = check(19200, "N", 1, [(100, 0)])
    assert run.ok()
