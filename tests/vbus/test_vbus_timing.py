"""Wire timing of the virtual bus, measured end to end, apart from what the kernel adds.

A writer (this process) writes a frame to drop0 in one call; a reader in another
process (a plain client: blocking ``read`` in raw mode, timestamps with
``time.perf_counter``, which is CLOCK_MONOTONIC on Linux and so shared between
processes) receives it on drop1.  Byte k is due at ``t_write + (k + 1) * char``.

A delivery crosses two pseudo-terminals (client -> hub, hub -> client), and what
each adds (a kernel work-queue hop and a wake-up: 20-250 us, depending on the
machine) is not the bus's doing.  So each attempt first measures the machine's
own bare pty latency ``L`` with the same reader (one ``os.write`` of one byte on a
pty master -> the reader's blocking ``os.read`` on its tty end, 1 ms apart), and
the bus is held to its fidelity (10 % of the elapsed wire time or 200 us,
whichever is larger) on what it controls:

* the end-to-end offset, the median over bytes of ``arrival - due``, minus
  ``2 * L`` (p50; the hub's own latency compensation counts as the bus's doing);
* spacing: each byte's ``arrival - due`` relative to that offset, within the
  fidelity of its elapsed wire time.  The offset is the reference rather than
  the first arrival because the first byte after a silence comes later than the
  rest: the reader wakes from a long sleep, which takes longer (measured with the
  bare pty too, after 20 ms idle, and taken off that byte's error); with the
  first arrival as the reference that one delay would count against every byte;
* the first-to-last-byte span, against the frame's wire time;
* gaps the sender leaves, kept between the two arrivals around them.

The raw end-to-end offset is reported (printed, and recorded as a test property)
and fails only beyond a sanity bound of one t3.5: a bus adding more than an
inter-frame silence to every delivery is no wire, whatever the reason.

The machine is shared (2 cores, a VM: timed waits occasionally wake milliseconds
late whatever the program), so a measurement is repeated up to 5 times and the
test passes when one run meets every bound; every run's figures are printed.
A run is judged only when the machine could carry the fidelity at all: when the
bare pty's own jitter (p99 - p50), measured before and again after the frame, is
within the 200 us floor.  On a
saturated machine (bare pty p99 of milliseconds: the kernel's pty work is a normal
priority kworker, behind every busy process) the kernel alone breaks the bound
for some bytes; when no run is judged and none passes, the test fails with its
figures, as unmeasurable here (it never skips: a skip would let CI pass unchecked).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
import tty
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
PTY_SAMPLES = 200  # one-byte writes 1 ms apart: ~0.25 s per measurement
PTY_COLD_SAMPLES = 15  # and 20 ms apart: 0.3 s


def quantile(values: list[float], q: float) -> float:
    srt = sorted(values)
    return srt[min(len(srt) - 1, round(q * (len(srt) - 1)))]


def bound_ns(elapsed_wire_ns: float) -> float:
    """The bus's fidelity: 10 % of the elapsed wire time or 200 us, whichever is larger."""
    return max(0.1 * elapsed_wire_ns, 200_000.0)


def t35_ns(baud: int, char_ns: int) -> float:
    """t3.5 (Serial Line V1.02, 2.5.1.1): 3.5 characters, fixed 1.75 ms above 19200 baud."""
    return 1_750_000.0 if baud > 19200 else 3.5 * char_ns


def start_reader(path: str, nbytes: int) -> subprocess.Popen[str]:
    reader = subprocess.Popen(
        [sys.executable, "-c", READER, path, str(nbytes)], stdout=subprocess.PIPE, text=True
    )
    assert reader.stdout is not None
    assert reader.stdout.readline().strip() == "ready"
    return reader


def finish_reader(reader: subprocess.Popen[str], nbytes: int) -> list[int]:
    """The reader's arrival time of every byte (a read of n bytes: n arrivals)."""
    assert reader.stdout is not None
    line = reader.stdout.readline()
    reader.wait(10)
    arrivals: list[int] = []
    for t, n in json.loads(line):
        arrivals += [t] * n
    assert len(arrivals) == nbytes
    return arrivals


@dataclass
class PtyLatency:
    p50_us: float  # warm: the reader woke 1 ms before (as between bytes at 9600 baud)
    p99_us: float
    cold_p50_us: float  # the reader idle for 20 ms (as before the first byte of a frame)

    @property
    def cold_extra_us(self) -> float:
        """What a wake-up from a long silence adds to a delivery, on this machine."""
        return max(0.0, self.cold_p50_us - self.p50_us)

    def __str__(self) -> str:
        return (
            f"bare pty latency p50 {self.p50_us:.0f} us, p99 {self.p99_us:.0f} us"
            f" (after 20 ms idle: p50 {self.cold_p50_us:.0f} us)"
        )


def measure_pty_latency(samples: int = PTY_SAMPLES, cold: int = PTY_COLD_SAMPLES) -> PtyLatency:
    """One os.write of one byte on a pty master -> the reader's blocking os.read."""
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        reader = start_reader(os.ttyname(slave), samples + cold)
        try:
            writes = []
            for i in range(samples + cold):
                time.sleep(0.001 if i < samples else 0.02)  # the reader waits in its read
                writes.append(time.perf_counter_ns())
                os.write(master, b"\x55")
            arrivals = finish_reader(reader, samples + cold)
        finally:
            if reader.poll() is None:
                reader.kill()
                reader.wait()
    finally:
        os.close(master)
        os.close(slave)
    lat = [(a - w) / 1e3 for a, w in zip(arrivals, writes, strict=True)]
    warm = lat[:samples]
    return PtyLatency(quantile(warm, 0.5), quantile(warm, 0.99), statistics.median(lat[samples:]))


@dataclass
class Run:
    baud: int
    fmt: str
    pty: PtyLatency
    pty_after: PtyLatency  # measured again right after the frame
    char_ns: int
    spacing_errs_us: tuple[float, ...]  # per byte: (a_k - due_k) - the offset
    spacing_margin: float  # max over bytes of |spacing err| / bound (<= 1 passes)
    span_err_us: float
    span_bound_us: float
    raw_offset_us: float  # median over bytes of arrival - due
    offset_bound_us: float
    sanity_bound_us: float  # t3.5
    gap_err_us: float | None = None
    gap_bound_us: float = 0.0
    realtime: bool = False

    @property
    def measurable(self) -> bool:
        """The bare pty's jitter, before and after the frame, is within the fidelity
        floor: the kernel alone cannot account for an error beyond the bound."""
        return all((p.p99_us - p.p50_us) * 1e3 <= bound_ns(0) for p in (self.pty, self.pty_after))

    @property
    def own_offset_us(self) -> float:
        """The end-to-end offset less what the two pty crossings add (2 * p50)."""
        return self.raw_offset_us - 2 * self.pty.p50_us

    def ok(self) -> bool:
        return (
            self.spacing_margin <= 1.0
            and abs(self.span_err_us) <= self.span_bound_us
            and abs(self.own_offset_us) <= self.offset_bound_us
            and abs(self.raw_offset_us) <= self.sanity_bound_us
            and (self.gap_err_us is None or abs(self.gap_err_us) <= self.gap_bound_us)
        )

    def figures(self) -> dict[str, float]:
        abs_errs = [abs(e) for e in self.spacing_errs_us]
        out = {
            "pty_p50_us": self.pty.p50_us,
            "pty_p99_us": self.pty.p99_us,
            "pty_cold_p50_us": self.pty.cold_p50_us,
            "spacing_abs_err_median_us": statistics.median(abs_errs),
            "spacing_abs_err_p99_us": quantile(abs_errs, 0.99),
            "spacing_abs_err_max_us": max(abs_errs),
            "span_err_us": self.span_err_us,
            "raw_offset_us": self.raw_offset_us,
            "own_offset_us": self.own_offset_us,
        }
        if self.gap_err_us is not None:
            out["gap_err_us"] = self.gap_err_us
        return out

    def __str__(self) -> str:
        f = self.figures()
        gap = "" if self.gap_err_us is None else f", gap err {self.gap_err_us:+.0f} us"
        return (
            f"{self.baud} {self.fmt}: {self.pty}; spacing |err| median"
            f" {f['spacing_abs_err_median_us']:.0f} us, p99 {f['spacing_abs_err_p99_us']:.0f}"
            f" max {f['spacing_abs_err_max_us']:.0f} us (worst err/bound"
            f" {self.spacing_margin:.2f}), span err {self.span_err_us:+.0f} us of"
            f" {self.span_bound_us:.0f}{gap}; end-to-end offset raw {self.raw_offset_us:+.0f} us"
            f" (sanity bound t3.5 {self.sanity_bound_us:.0f}), minus 2 x pty p50"
            f" {self.own_offset_us:+.0f} us (bound {self.offset_bound_us:.0f})"
        )


def measure(baud: int, parity: str, stopbits: int, parts: list[tuple[int, float]]) -> Run:
    """Send `parts` ([(nbytes, silence_chars_before), ...]) and time the arrivals."""
    pty = measure_pty_latency()
    total = sum(n for n, _ in parts)
    with VirtualBus(2, baudrate=baud, parity=parity, stopbits=stopbits) as bus:
        char = bus.char_ns
        reader = start_reader(bus.paths[1], total)
        try:
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
            arrivals = finish_reader(reader, total)
            realtime = bus.realtime
            os.close(fd)
        finally:
            if reader.poll() is None:
                reader.kill()
                reader.wait()
    pty_after = measure_pty_latency()
    first_due = due[0] - char  # the write: byte k has been on the wire (k + 1) chars
    errs = [a - d for a, d in zip(arrivals, due, strict=True)]
    offset = statistics.median(errs)
    spacing = [e - offset for e in errs]
    spacing[0] -= round(pty.cold_extra_us * 1e3)  # the reader's wake-up after the silence
    margins = [abs(e) / bound_ns(d - first_due) for e, d in zip(spacing, due, strict=True)]
    gap_err = None
    gap_bound = 0.0
    if len(parts) > 1:
        k = parts[0][0]
        assert gap_due is not None
        gap_err = (arrivals[k] - arrivals[k - 1] - char - gap_due) / 1e3
        # the difference of two arrivals, each held to the fidelity bound
        gap_bound = 2 * bound_ns(gap_due) / 1e3
    return Run(
        baud=baud,
        fmt=f"8{parity}{stopbits}",
        pty=pty,
        pty_after=pty_after,
        char_ns=char,
        spacing_errs_us=tuple(e / 1e3 for e in spacing),
        spacing_margin=max(margins),
        span_err_us=((arrivals[-1] - arrivals[0]) - (due[-1] - due[0])) / 1e3,
        span_bound_us=bound_ns(due[-1] - due[0]) / 1e3,
        raw_offset_us=offset / 1e3,
        offset_bound_us=bound_ns(char) / 1e3,
        sanity_bound_us=t35_ns(baud, char) / 1e3,
        gap_err_us=gap_err,
        gap_bound_us=gap_bound,
        realtime=realtime,
    )


def check(
    baud: int,
    parity: str,
    stopbits: int,
    parts: list[tuple[int, float]],
    record_property: pytest.RecordProperty | None = None,
) -> Run:
    runs = []
    for _ in range(ATTEMPTS):
        run = measure(baud, parity, stopbits, parts)
        runs.append(run)
        after = f"; after it: p50 {run.pty_after.p50_us:.0f} us, p99 {run.pty_after.p99_us:.0f} us"
        print(f"vbus timing {run}{after}{'' if run.measurable else ' [pty jitter > 200 us]'}")
        if run.ok():
            if record_property is not None:
                for key, value in run.figures().items():
                    record_property(key, round(value, 1))
            return run
    report = (
        "\n".join(map(str, runs))
        + f"\n(hub thread real-time: {runs[-1].realtime}; load average: {os.getloadavg()})"
    )
    # A machine too loaded to measure on fails too (after ATTEMPTS runs), never skips:
    # a skip would let CI pass without the check
    if not any(run.measurable for run in runs):
        pytest.fail(
            "unmeasurable here: the bare pty's own jitter (p99 - p50) exceeded the 200 us"
            " fidelity floor in every run, and no run met the bounds anyway:\n" + report
        )
    pytest.fail("delivery timing out of bounds in every run:\n" + report)


@pytest.mark.wall_clock
@pytest.mark.parametrize("baud", [9600, 115200])
def test_256_byte_frame_takes_its_wire_time(
    baud: int, record_property: pytest.RecordProperty
) -> None:
    run = check(baud, "E", 1, [(256, 0)], record_property)
    assert run.ok()


@pytest.mark.wall_clock
@pytest.mark.parametrize("baud", [9600, 115200])
def test_gaps_the_sender_leaves_are_kept(baud: int, record_property: pytest.RecordProperty) -> None:
    # 8 bytes, a silence of 5 character times (more than t3.5), 8 bytes.
    run = check(baud, "E", 1, [(8, 0), (8, 5.0)], record_property)
    assert run.gap_err_us is not None and abs(run.gap_err_us) <= run.gap_bound_us


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


@pytest.mark.wall_clock
def test_8n1_frame_takes_its_wire_time() -> None:
    """The 10-bit character of 8N1 on the wire: 100 bytes at 19200 baud."""
    run = check(19200, "N", 1, [(100, 0)])
    assert run.ok()
