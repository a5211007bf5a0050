"""The poller's benchmark (issue 11): point updates per second against naive loops,
utilisation under overload, one slave of eight unplugged, CPU per point update.

    python bench/bench_poller.py [--seconds 5] [--bauds 19200,115200] [--no-write]

Per baud rate: a virtual bus (``pyrtu vbus``, its own process) with eight
simulated drives (``pyrtu simulate``, one process each: CFW701, CFW100, CFW320,
CV100, ACU, ACT, CFW701, CV100 at addresses 1-8) and 208 registers of points
spread as a configuration spreads them (WEG: P000-P007, P048/P049, P100-P103,
P220-P228, P401-P403, P680-P683; CV100: 0x3200-0x3203, 0x3300-0x3322; Vectron:
five 16-bit parameters each, one per request).  The poller runs in this process
(its CPU time is this process's); the naive loops read one point per request, in
a loop, with pyrtu's `Master` and with pymodbus's `AsyncModbusSerialClient`.

Writes the section "## The poller (issue 11)" of bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pyrtu import Master
from pyrtu.aio import run as aio_run
from pyrtu.devices import cv100 as C
from pyrtu.poller import Bus, Device, Limits, Point, Poller, SlaveState, make_config
from pyrtu.poller.profiles import device_limits

BENCH = Path(__file__).resolve().parent
RESULTS = BENCH / "RESULTS.md"
HEADING = "## The poller (issue 11)"
BEGIN, END = "<!-- poller:begin (bench/bench_poller.py) -->", "<!-- poller:end -->"
DRIVES = ("cfw701", "cfw100", "cfw320", "cv100", "acu", "act", "cfw701", "cv100")
TIMEOUT = 0.1
WEG_REGS = [*range(0, 8), 48, 49, *range(100, 104), *range(220, 229), 401, 402, 403,
            *range(680, 684)]  # fmt: skip
CV_REGS = [*range(C.MAIN_SETTING - 1, C.MAIN_SETTING + 3), *range(0x3300, 0x3323)]
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
    its master)."""
    from pyrtu.aio import AsyncMaster

    with farm(baud) as (path, _sims):

        async def bare() -> float:
            async with AsyncMaster(path, baud, parity="N", timeout=TIMEOUT) as m:
                for _ in range(20):
                    await m.read_holding_registers(4, 0x3300, 10)
                c0, t0, n = time.process_time(), time.monotonic(), 0
                while time.monotonic() - t0 < seconds:
                    await m.read_holding_registers(4, 0x3300, 10)
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
                await asyncio.sleep(seconds)
                n = poller.report()[0].transactions
                return 1e6 * (time.process_time() - c0) / n

        return {"bare_us_per_tx": aio_run(bare()), "poller_us_per_tx": aio_run(polled())}


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
    out["alive"], out["dead"], out["naive_dead"] = alive, dead, naive_dead
    print(json.dumps(out, default=str), file=sys.stderr, flush=True)
    others = range(1, 8)
    out["others_ratio"] = min(dead["per_slave"][s] / alive["per_slave"][s] for s in others)
    out["naive_others_ratio"] = min(
        naive_dead["per_slave"][s] / out["naive_pyrtu"]["per_slave"][s] for s in others
    )
    return out


def section(
    runs: list[dict[str, Any]], command: str, pure: dict[str, float], over: dict[str, float]
) -> str:
    lines = [
        HEADING, "", BEGIN, "",
        f"Command: `{command}` (one run; {os.cpu_count()} CPUs, Python "
        f"{sys.version.split()[0]}). Eight simulated drives on the virtual bus (hub and "
        "drives in their own processes), 208 registers of points; point updates per "
        "second counted over the measuring window, the poller after 1.5 s of warm-up "
        "(holes learned, turnarounds measured). Master timeout 100 ms.",
        "",
        "The poller drives `pyrtu.aio.AsyncMaster` (the default) on `pyrtu.aio.run`'s "
        "loop; \"thread\" is `Poller(master=\"thread\")`, the sync `Master` on a "
        "worker thread. All points at 1 ms intervals: the bus is overloaded and the "
        "poller runs flat out.",
        "",
        "| baud | poller updates/s | blocks | naive (a) pyrtu | naive (b) pymodbus | "
        "poller / (a) | poller / (b) | utilisation (overload) | CPU/update | "
        "thread: updates/s, utilisation, CPU/update |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for r in runs:
        p, a, b = r["poller"], r["naive_pyrtu"], r["naive_pymodbus"]
        lines.append(
            f"| {r['baud']} | {p['updates_per_s']:.0f} | {p['blocks']} | "
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
    blocks = runs[0]["poller"]["blocks"]
    lo, hi = f"{min(gains):.1f}", f"{max(gains):.1f}"
    gain = lo if lo == hi else f"{lo}-{hi}"
    lines += [
        "",
        "Reading: the poller's gain over a naive loop is bounded by how many requests "
        f"it saves. These 208 points take {blocks} requests a cycle against 208: the WEG "
        "simulators answer exception 2 across their unmapped registers, so each WEG "
        "drive's 30 points stay six blocks, and the Vectron drives read one register "
        f"per FC 03 (10 of the {blocks} requests, each with the manual's 10 ms response "
        f"delay). The measured {gain}x (target 10x) is that "
        "ratio less the longer answers; "
        "the target is not met with this point set. Utilisation under overload meets "
        "its target (>= 0.95), and so does an unplugged slave (the others within 5 %, "
        "its probes within 5 % of the bus). CPU per point update is this process's "
        "CPU time (event loop, master and poller) over the updates, on a 2-CPU machine "
        "shared with the hub and the eight simulator processes. The sans-I/O layers "
        "alone (scheduler, decoding, change-only tracking; `scheduler_cpu`, fake clock) "
        f"take {pure['us_per_tx']:.1f} us per transaction, {pure['us_per_update']:.1f} us "
        "per point update: the rest is the event loop and the master. Reading the "
        "same 10 registers of one CV100 back to back at 115200 (`overhead`), a bare "
        f"`AsyncMaster` loop takes {over['bare_us_per_tx']:.0f} us of CPU per "
        f"transaction and the poller {over['poller_us_per_tx']:.0f} us (10 updates each).",
        "",
        END,
        "",
    ]
    return "\n".join(lines)


def write_section(text: str) -> None:
    old = RESULTS.read_text() if RESULTS.exists() else ""
    if BEGIN in old:
        start = old.rindex("\n" + HEADING, 0, old.index(BEGIN)) + 1
        stop = old.index(END) + len(END) + 1
        new = old[:start] + text + old[stop:]
    else:
        new = old.rstrip("\n") + "\n\n" + text
    RESULTS.write_text(new)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--bauds", default="19200,115200")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--json", type=Path, default=None, help="also save the figures here")
    ap.add_argument("--from-json", type=Path, default=None,
                    help="write the section from figures of --json, measuring nothing")  # fmt: skip
    args = ap.parse_args()
    if args.from_json is not None:
        runs = json.loads(args.from_json.read_text())
    else:
        runs = [measure(int(b), args.seconds) for b in args.bauds.split(",")]
    command = "python bench/bench_poller.py " + " ".join(
        a for a in sys.argv[1:] if a != "--from-json" and not a.endswith(".json")
    )
    text = section(runs, command.strip(), scheduler_cpu(), overhead(args.seconds))
    print(text)
    print(json.dumps(runs, indent=1, default=str), file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(runs, indent=1, default=str))
    if not args.no_write:
        write_section(text)


if __name__ == "__main__":
    main()
