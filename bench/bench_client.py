"""Issue 10: the master on the sans-I/O client protocol, on the virtual bus.

    python bench/bench_client.py [--json FILE] [--quick]

Every bus is a separate ``pyrtu vbus`` process (its hub keeps the byte timing away
from the GIL of the process under test) and every server a separate process, so
the CPU figures are the master's own:

1. single bus, FC 03 x 10 registers, byte-timed delivery, specification timing on
   both sides, the pyrtu slave (tests/peers/pyrtu_slave.py) on drop 1, at 9600 and
   115200 baud 8N1: the sync `Master` and `AsyncMaster` (on `pyrtu.drivers.aio.run`'s
   microsecond-timer loop): transactions/s, ratio to the wire limit
   1 / (33 characters + 2 x t3.5), master CPU per transaction (the process's CPU
   time, as the libmodbus client counts its own: an xfer thread's included);
2. pymodbus's ``AsyncModbusSerialClient`` on the same bus against the same slave,
   at 115200: transactions/s and CPU per transaction, and the ratios;
3. 8 buses at 115200, a simulated drive on each (one ``pyrtu simulate cfw100 --port
   ... --port ...`` process serving the 8 drives), polled concurrently by one
   `AsyncMaster` process (8 masters in one event loop): every bus's ratio to the
   wire limit and the process's total CPU.

bench/report.py runs it (``--json``) for bench/RESULTS.md; the summary goes to stdout.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path.insert(0, str(ROOT / "tests"))

import peers.pattern as pattern  # type: ignore[import-not-found]  # noqa: E402
from peers.tools import (  # type: ignore[import-not-found]  # noqa: E402
    PeerBinaries,
    build_peers,
    libmodbus_bench,
)

from pyrtu.core.line import LineConfig  # noqa: E402
from pyrtu.drivers.aio import AsyncMaster  # noqa: E402
from pyrtu.drivers.aio import run as aio_run  # noqa: E402
from pyrtu.drivers.master import Master  # noqa: E402
from pyrtu.pdu.errors import FrameError, NoResponseError  # noqa: E402

SLAVE = 7
COUNT = 10
EXPECTED = pattern.holdings(SLAVE, 0, COUNT)
HEADING = "## Sans-I/O client (issue 10)"
BEGIN, END = "<!-- client:begin (bench/bench_client.py) -->", "<!-- client:end -->"


def wire_limit(baudrate: int, chars: int = 33) -> float:
    """Transactions per second the wire allows: ``chars`` characters (request and
    answer; 33 for FC 03 x 10) and two t3.5 silences."""
    line = LineConfig(baudrate=baudrate, parity="N")
    return 1.0 / (chars * line.char_time + 2 * line.t35_time)


#: the drive poll on the 8 buses: FC 03 of P001-P007 (speed reference, speed, current,
#: ...: the CFW100's longest run of consecutive parameters), 8 + 19 characters
DRIVE_START, DRIVE_COUNT, DRIVE_CHARS = 1, 7, 8 + 5 + 2 * 7
#: the simulated CFW100 answers 2 ms after t3.5 (pyrtu.devices.weg_sim.RESPONSE_DELAY)
DRIVE_DELAY = 0.002


def machine_ticks() -> tuple[int, int]:
    """(busy, total) clock ticks of the whole machine so far (/proc/stat): the
    kernel's own work on the ptys (their flip-buffer workers) is in neither the
    hubs' nor the drives' CPU."""
    with open("/proc/stat", encoding="ascii") as f:
        fields = [int(v) for v in f.readline().split()[1:9]]
    idle = fields[3] + fields[4]  # idle, iowait
    return sum(fields) - idle, sum(fields)


def cpu_of(pid: int) -> float:
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextlib.contextmanager
def process(
    argv: list[str], ready_lines: int = 0, extra_env: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen[str], list[str]]]:
    """A child process; the first ``ready_lines`` lines of its stdout are returned."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), **(extra_env or {}))
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        lines = []
        assert proc.stdout is not None
        for _ in range(ready_lines):
            lines.append(proc.stdout.readline().strip())
        yield proc, lines
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@contextlib.contextmanager
def vbus(
    baudrate: int, drops: int = 2, loop: str = "c", stats: bool = False
) -> Iterator[tuple[list[str], int]]:
    """``pyrtu vbus`` in its own process: (drop paths, pid).  ``loop="python"`` runs
    its hub on the Python loop (PYRTU_PURE=1 in that process only); ``stats``: it
    prints its counters on stderr when it stops."""
    with tempfile.TemporaryDirectory() as tmp:
        argv = [sys.executable, "-m", "pyrtu", "vbus", "--drops", str(drops)]
        argv += ["--baud", str(baudrate), "--parity", "N", "--dir", tmp]
        argv += ["--stats"] if stats else []
        env = {"PYRTU_PURE": "1"} if loop == "python" else None
        with process(argv, drops, env) as (proc, paths):
            yield paths, proc.pid


@contextlib.contextmanager
def slave(path: str, baudrate: int) -> Iterator[int]:
    argv = [sys.executable, str(ROOT / "tests/peers/pyrtu_slave.py"), path, str(SLAVE)]
    argv += ["--baud", str(baudrate)]
    with process(argv, 1) as (proc, lines):  # the peer prints READY once serving
        if not lines[0].startswith("READY"):
            raise RuntimeError(f"the pyrtu slave did not start: {lines[0]!r}")
        yield proc.pid


#: the simulated drives of the 8-bus run: (address, FC 03 start, count, the response
#: delay its manual documents and the simulator keeps).  The CFW100 answers 2 ms after
#: t3.5, which caps a bus at 127.4/s of the 171/s wire limit; the CV100 (RTU mode)
#: documents no delay, so its bus can approach the wire limit itself.
DRIVES = {
    "cfw100": (1, DRIVE_START, DRIVE_COUNT, DRIVE_DELAY),  # P001-P007
    "cv100": (5, 0x3300, 7, 0.0),  # status words and monitored values (U0)
    # not a drive: bench/floor_slave.c, the least a slave keeping t3.5 does (C, one
    # process per bus), so that a run shows what the bus itself allows the master
    "floor": (5, 0x3300, 7, 0.0),
}


@contextlib.contextmanager
def drives(paths: list[str], baudrate: int, name: str = "cfw100") -> Iterator[int]:
    """One ``pyrtu simulate`` process, a drive on each of ``paths`` (``--port`` given
    once per path: the drives share one event loop); "floor": bench/floor_slave.c on
    each."""
    if name == "floor":
        with floor_slaves(paths, baudrate) as pid:
            yield pid
        return
    argv = [sys.executable, "-m", "pyrtu", "simulate", name, "--json"]
    for path in paths:
        argv += ["--port", path]
    argv += ["--baudrate", str(baudrate), "-P", "N", "--address", str(DRIVES[name][0])]
    with process(argv, 1) as (proc, lines):
        if '"ready"' not in lines[0]:
            raise RuntimeError(f"pyrtu simulate did not start: {lines[0]!r}")
        yield proc.pid


@contextlib.contextmanager
def floor_slaves(paths: list[str], baudrate: int) -> Iterator[int]:
    """bench/floor_slave.c (compiled here with the system's cc) on each of ``paths``;
    the first one's pid."""
    exe = Path(tempfile.mkdtemp(prefix="pyrtu-floor-")) / "floor_slave"
    subprocess.run(["cc", "-O2", "-o", str(exe), str(BENCH / "floor_slave.c")], check=True)
    t35_us = round(LineConfig(baudrate=baudrate, parity="N").t35_time * 1e6)
    with contextlib.ExitStack() as stack:
        pids = []
        for path in paths:
            proc, lines = stack.enter_context(process([str(exe), path, str(t35_us)], 1))
            if lines[0] != "READY":
                raise RuntimeError(f"floor_slave did not start: {lines[0]!r}")
            pids.append(proc.pid)
        yield pids[0]


def sync_master(path: str, baudrate: int, n: int) -> dict[str, float]:
    with Master(path, baudrate, parity="N", timeout=1.0) as m:
        for _ in range(5):
            assert m.read_holding_registers(SLAVE, 0, COUNT) == EXPECTED
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(n):
            if m.read_holding_registers(SLAVE, 0, COUNT) != EXPECTED:
                raise AssertionError("wrong value")
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        assert m.counters["timeouts"] == m.counters["frame_errors"] == 0
    return {"tps": n / wall, "cpu_us": cpu / n * 1e6}


def async_master(path: str, baudrate: int, n: int) -> dict[str, float]:
    async def main() -> dict[str, float]:
        async with AsyncMaster(path, baudrate, parity="N", timeout=1.0) as m:
            for _ in range(5):
                assert await m.read_holding_registers(SLAVE, 0, COUNT) == EXPECTED
            c0, t0 = time.process_time(), time.perf_counter()
            for _ in range(n):
                if await m.read_holding_registers(SLAVE, 0, COUNT) != EXPECTED:
                    raise AssertionError("wrong value")
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            assert m.counters["timeouts"] == m.counters["frame_errors"] == 0
        return {"tps": n / wall, "cpu_us": cpu / n * 1e6}

    result: dict[str, float] = aio_run(main())
    return result


def pymodbus_master(path: str, baudrate: int, n: int) -> dict[str, float]:
    from pymodbus.client import AsyncModbusSerialClient

    async def main() -> dict[str, float]:
        client = AsyncModbusSerialClient(
            path, baudrate=baudrate, parity="N", stopbits=1, bytesize=8, timeout=1.0, retries=0
        )
        await client.connect()
        try:
            for _ in range(5):
                rr = await client.read_holding_registers(0, count=COUNT, device_id=SLAVE)
                assert list(rr.registers) == EXPECTED
            c0, t0 = time.process_time(), time.perf_counter()
            ok = 0
            for _ in range(n):
                rr = await client.read_holding_registers(0, count=COUNT, device_id=SLAVE)
                ok += list(rr.registers) == EXPECTED
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        finally:
            client.close()
        return {"tps": n / wall, "cpu_us": cpu / n * 1e6, "ok": ok}

    return asyncio.run(main())


_BASELINE = r"""
import sys, time
from pyrtu import Master
path, n, baud = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
with Master(path, baud, parity="N", timeout=1.0) as m:
    for _ in range(5):
        m.read_holding_registers(7, 0, 10)
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(n):
        m.read_holding_registers(7, 0, 10)
    print(n / (time.perf_counter() - t0), (time.process_time() - c0) / n * 1e6)
"""

#: the AsyncMaster of the checkout before, on `pyrtu.drivers.aio.run` as `async_master`
_BASELINE_ASYNC = r"""
import sys, time
from pyrtu.aio import AsyncMaster, run
path, n, baud = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
async def main():
    async with AsyncMaster(path, baud, parity="N", timeout=1.0) as m:
        for _ in range(5):
            await m.read_holding_registers(7, 0, 10)
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(n):
            await m.read_holding_registers(7, 0, 10)
        print(n / (time.perf_counter() - t0), (time.process_time() - c0) / n * 1e6)
run(main())
"""


def cpu_rounds(
    bauds: Iterable[int],
    rounds: int,
    one_round: Callable[[int, str, int, int], Iterable[tuple[str, float]]],
) -> Iterator[tuple[int, dict[str, float]]]:
    """Per baud rate, on one virtual bus and slave: ``rounds`` rounds of
    ``one_round(i, path, baudrate, n)`` (its (name, CPU µs per transaction) pairs, each
    program in a fresh interpreter), each followed by the libmodbus client; the
    medians by name ("libmodbus" included).  ``n``: transactions per program."""
    peers = build_peers(Path(tempfile.mkdtemp(prefix="pyrtu-peers-")))
    for baud in bauds:
        n = 40 if baud < 19200 else 300
        runs: dict[str, list[float]] = {}
        with vbus(baud) as (paths, _hub), slave(paths[1], baud):
            for i in range(rounds):
                for name, cpu in one_round(i, paths[0], baud, n):
                    runs.setdefault(name, []).append(cpu)
                lm = libmodbus_master(peers, paths[0], baud, n)
                runs.setdefault("libmodbus", []).append(lm["cpu_us"])
        yield baud, {k: statistics.median(v) for k, v in runs.items()}


def libmodbus_master(binaries: PeerBinaries, path: str, baudrate: int, n: int) -> dict[str, float]:
    """The libmodbus client (C, tests/peers/libmodbus_client.c) on the same bus: the
    C reference for CPU per transaction (it keeps no t3.5 before its requests)."""
    r = libmodbus_bench(binaries, path, SLAVE, n, baudrate=baudrate, warmup=5)
    if r["errors"] or r["wrong"]:
        raise AssertionError(f"libmodbus client: {r}")
    return {"tps": float(r["tps"]), "cpu_us": float(r["cpu_us_per_tx"])}


def baseline_master(
    root: str, path: str, baudrate: int, n: int, program: str = _BASELINE
) -> dict[str, float]:
    """The sync Master (or ``program``) of another checkout (``--baseline DIR``), same
    bus, same slave."""
    env = dict(os.environ, PYTHONPATH=root)
    argv = [sys.executable, "-c", program, path, str(n), str(baudrate)]
    for _ in range(3):  # a loaded machine can make a read late: one error ends a run
        out = subprocess.run(argv, env=env, cwd=root, capture_output=True, text=True)
        if not out.returncode:
            break
        print(f"baseline run failed, again: {out.stderr.strip()[-300:]}", file=sys.stderr)
    else:
        raise RuntimeError(f"the baseline failed: {out.stderr.strip()[-2000:]}")
    tps, cpu = (float(x) for x in out.stdout.split())
    return {"tps": tps, "cpu_us": cpu}


def protocol_only(baudrate: int, n: int = 20000) -> float:
    """CPU per transaction of the client protocol alone, synthetic time, no I/O (hot
    caches): start, send, the answer in two reads, the result."""
    from pyrtu.core import _backend
    from pyrtu.pdu.requests import read_holding_registers
    from pyrtu.protocol.client import ClientProtocol

    be = _backend.active
    proto = ClientProtocol(LineConfig(baudrate=baudrate, parity="N"), timeout=1.0, backend=be)
    answer = be.add_crc(bytes((SLAVE, 3, 2 * COUNT)) + bytes(2 * COUNT))
    t = 1.0
    c0 = time.process_time()
    for _ in range(n):
        proto.start(*read_holding_registers(SLAVE, 0, COUNT), now=t)
        proto.handle_timer(t + 0.01)
        proto.data_to_send()
        proto.transmitted(t + 0.011)
        proto.receive_data(answer[:5], t + 0.012)
        proto.ready_at(t + 0.012)
        proto.receive_data(answer[5:], t + 0.014)
        proto.result()
        t += 0.02
    return (time.process_time() - c0) / n * 1e6


def single_bus(
    baudrate: int,
    n: int,
    rounds: int,
    pymodbus: bool,
    baseline: str | None = None,
    peers: PeerBinaries | None = None,
) -> dict[str, Any]:
    out: dict[str, Any] = {"baudrate": baudrate, "wire_limit": wire_limit(baudrate)}
    with vbus(baudrate) as (paths, hub_pid), slave(paths[1], baudrate) as slave_pid:
        runs: dict[str, list[dict[str, float]]] = {
            "sync": [],
            "asyncio": [],
            "pymodbus": [],
            "baseline": [],
            "baseline_async": [],
            "libmodbus": [],
        }
        for _ in range(rounds):  # interleaved: the machine is shared and drifts
            if baseline:
                runs["baseline"].append(baseline_master(baseline, paths[0], baudrate, n))
                runs["baseline_async"].append(
                    baseline_master(baseline, paths[0], baudrate, n, _BASELINE_ASYNC)
                )
            runs["sync"].append(sync_master(paths[0], baudrate, n))
            runs["asyncio"].append(async_master(paths[0], baudrate, n))
            if pymodbus:
                runs["pymodbus"].append(pymodbus_master(paths[0], baudrate, max(n // 2, 20)))
            if peers is not None:
                runs["libmodbus"].append(libmodbus_master(peers, paths[0], baudrate, n))
        for name, rs in runs.items():
            if rs:
                out[name] = {
                    "tps": statistics.median(r["tps"] for r in rs),
                    "cpu_us": statistics.median(r["cpu_us"] for r in rs),
                    "rounds": len(rs),
                    "n": n,
                }
                out[name]["ratio"] = out[name]["tps"] / out["wire_limit"]
        out["hub_cpu_s"] = cpu_of(hub_pid)
        out["slave_cpu_s"] = cpu_of(slave_pid)
    return out


def eight_buses(
    baudrate: int,
    seconds: float,
    buses: int = 8,
    drive_name: str = "cfw100",
    loop: str = "c",
    event_loop: str = "pyrtu",
) -> dict[str, Any]:
    """``buses`` buses, a simulated drive on each, polled by one AsyncMaster process
    (this one) for ``seconds``: FC 03 of 7 registers (19-byte answers).  ``loop``: the
    hubs' loop ("c": the C I/O thread; "python": the Python loop); ``event_loop``: the
    masters' asyncio loop (`EVENT_LOOPS`)."""
    address, start, count, delay = DRIVES[drive_name]
    with contextlib.ExitStack() as stack:
        paths: list[str] = []
        drive_paths: list[str] = []
        hubs: list[int] = []
        for _ in range(buses):
            p, pid = stack.enter_context(vbus(baudrate, loop=loop, stats=True))
            paths.append(p[0])
            drive_paths.append(p[1])
            hubs.append(pid)
        drive_pids = [stack.enter_context(drives(drive_paths, baudrate, drive_name))]
        counts = [0] * buses
        busy = [0.0]  # the machine's busy cores over the polling window

        async def main() -> tuple[float, float, float, float, float]:
            masters = [AsyncMaster(p, baudrate, parity="N", timeout=1.0) for p in paths]
            try:
                for m in masters:  # warm-up: the drive is up and answers
                    for attempt in range(10):
                        try:
                            await m.read_holding_registers(address, start, count)
                            break
                        except NoResponseError:
                            if attempt == 9:
                                raise
                stop = time.perf_counter() + seconds

                async def poll(i: int, m: AsyncMaster) -> None:
                    while time.perf_counter() < stop:
                        try:
                            await m.read_holding_registers(address, start, count)
                        except (NoResponseError, FrameError):
                            continue  # counted by the master (timeouts, frame errors)
                        counts[i] += 1

                errors0 = sum(m.counters["timeouts"] + m.counters["frame_errors"] for m in masters)
                hub0 = sum(cpu_of(h) for h in hubs)
                drive0 = sum(cpu_of(d) for d in drive_pids)
                r0 = resource.getrusage(resource.RUSAGE_SELF)
                m0 = machine_ticks()
                t0 = time.perf_counter()
                await asyncio.gather(*(poll(i, m) for i, m in enumerate(masters)))
                wall = time.perf_counter() - t0
                m1 = machine_ticks()
                busy[0] = (m1[0] - m0[0]) / max(1, m1[1] - m0[1]) * (os.cpu_count() or 1)
                r1 = resource.getrusage(resource.RUSAGE_SELF)
                hub_cpu = sum(cpu_of(h) for h in hubs) - hub0
                drive_cpu = sum(cpu_of(d) for d in drive_pids) - drive0
                cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
                errors = sum(m.counters["timeouts"] + m.counters["frame_errors"] for m in masters)
                return wall, cpu, float(errors - errors0), hub_cpu, drive_cpu
            finally:
                for m in masters:
                    await m.close()

        wall, cpu, errors, hub_cpu, drive_cpu = EVENT_LOOPS[event_loop](main())
    limit = wire_limit(baudrate, DRIVE_CHARS)
    with_delay = 1.0 / (1.0 / limit + delay)
    tps = [c / wall for c in counts]
    return {
        "baudrate": baudrate,
        "buses": buses,
        "drive": drive_name,
        "response_delay_s": delay,
        "hub_loop": loop,
        "event_loop": event_loop,
        "seconds": wall,
        "tps": tps,
        "ratios": [t / limit for t in tps],
        "wire_limit": limit,
        "limit_with_delay": with_delay,
        "ratios_with_delay": [t / with_delay for t in tps],
        "process_cpu_s": cpu,
        "process_cpu_share": cpu / wall,
        "cpu_us_per_tx": cpu / sum(counts) * 1e6,
        "errors": errors,
        "hub_cpu_s_total": hub_cpu,
        "drive_cpu_s_total": drive_cpu,
        "machine_busy_cores": busy[0],
        "machine_cores": os.cpu_count() or 1,
    }


def _uvloop_run(main: Any) -> Any:
    import uvloop  # type: ignore[import-not-found]

    return uvloop.run(main)


#: the masters' event loops: pyrtu.drivers.aio.run's select() loop, plain asyncio.run (epoll),
#: uvloop (libuv)
EVENT_LOOPS: dict[str, Any] = {"pyrtu": aio_run, "asyncio": asyncio.run, "uvloop": _uvloop_run}


def compare_loops(rounds: int, seconds: float, buses: int, drive: str, out: Path | None) -> None:
    """``buses`` buses at 115200 under each event loop, interleaved ``rounds`` times:
    per loop the minimum and median of the buses' ratios to the wire limit."""
    rows: dict[str, list[float]] = {k: [] for k in EVENT_LOOPS}
    cpu: dict[str, list[float]] = {k: [] for k in EVENT_LOOPS}
    for _ in range(rounds):
        for name in EVENT_LOOPS:
            e = eight_buses(115200, seconds, buses, drive, event_loop=name)
            rows[name] += e["ratios"]
            cpu[name].append(e["cpu_us_per_tx"])
            print(name, " ".join(f"{r:.3f}" for r in e["ratios"]), flush=True)
    print(f"| event loop | buses | ratio to wire limit (min / median), {drive} | CPU us/tx |")
    print("|---|---:|---:|---:|")
    for name, rs in rows.items():
        print(
            f"| {name} | {buses} | {min(rs):.3f} / {statistics.median(rs):.3f} |"
            f" {statistics.median(cpu[name]):.0f} |"
        )
    if out is not None:
        saved = {"rounds": rounds, "seconds": seconds, "buses": buses, "drive": drive}
        out.write_text(json.dumps({**saved, "ratios": rows, "cpu_us_per_tx": cpu}, indent=1))


def eight_line(e: dict[str, Any]) -> str:
    """One row of the hub comparison (bench/RESULTS.md, "C hub" subsection)."""
    return (
        f"| {e['drive']} | {e['hub_loop']} | {min(e['ratios']):.3f} / "
        f"{statistics.median(e['ratios']):.3f} | {min(e['ratios_with_delay']):.3f} | "
        f"{sum(e['tps']):.0f} | {e['process_cpu_share'] * 100:.0f}% | "
        f"{e['hub_cpu_s_total'] / e['seconds'] * 100:.0f}% | "
        f"{e['drive_cpu_s_total'] / e['seconds'] * 100:.0f}% | {int(e['errors'])} |"
    )


def section(data: dict[str, Any]) -> str:
    lines = [
        HEADING,
        "",
        BEGIN,
        "",
        f"`python bench/bench_client.py`, one run, {data['when']}. {data['machine']}.",
        "",
        "FC 03, 10 holding registers, every answer checked.  Each bus is a `pyrtu vbus`",
        "process (byte-timed delivery) and each server a process of its own: CPU is the",
        "master's thread.  Specification timing on both sides (t3.5 = 3.5 characters up to",
        "19200 baud, 1750 µs above).  Wire limit = 1 / (33 characters + 2 x t3.5).  Medians",
        f"over {data['rounds']} interleaved rounds.  The asyncio master runs on",
        "`pyrtu.drivers.aio.run` (a select() loop: microsecond timers; the default epoll loop",
        "rounds every timer up to a millisecond).",
        "",
        "| baud | master | transactions/s | wire limit /s | ratio | master CPU µs/tx |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for bus in data["single"]:
        for name in ("baseline", "sync", "baseline_async", "asyncio", "pymodbus", "libmodbus"):
            r = bus.get(name)
            if r:
                label = {
                    "sync": "pyrtu Master",
                    "asyncio": "pyrtu AsyncMaster",
                    "baseline": f"pyrtu Master before (`{data.get('baseline_rev', '?')}`)",
                    "baseline_async": "pyrtu AsyncMaster before "
                    f"(`{data.get('baseline_rev', '?')}`)",
                    "libmodbus": "libmodbus client (C; no t3.5 before its requests)",
                }.get(name, "pymodbus AsyncModbusSerialClient")
                lines.append(
                    f"| {bus['baudrate']} | {label} | {r['tps']:.1f} | {bus['wire_limit']:.1f} | "
                    f"**{r['ratio']:.3f}** | {r['cpu_us']:.1f} |"
                )
    lines.append("")
    if "protocol_us" in data:
        lines.append(
            f"- the client protocol alone (synthetic time, no I/O, hot caches): "
            f"**{data['protocol_us']:.1f} µs** per transaction"
        )
    for bus in data["single"]:
        for before, now, who in (
            ("baseline", "sync", "Master"),
            ("baseline_async", "asyncio", "AsyncMaster"),
        ):
            if bus.get(before):
                b, s_ = bus[before], bus[now]
                lines.append(
                    f"- {bus['baudrate']} baud, {who} now / before, same bus and slave, "
                    f"interleaved: CPU per transaction **{s_['cpu_us'] / b['cpu_us']:.2f}x**, "
                    f"transactions/s {s_['tps'] / b['tps']:.2f}x"
                )
    for bus in data["single"]:
        lm = bus.get("libmodbus")
        if lm and bus.get("baseline_async"):
            b, ba = bus["baseline"], bus["baseline_async"]
            lines.append(
                f"- {bus['baudrate']} baud, before, CPU per transaction against the libmodbus "
                f"client: Master **{b['cpu_us'] / lm['cpu_us']:.2f}x**, AsyncMaster "
                f"**{ba['cpu_us'] / lm['cpu_us']:.2f}x**"
            )
    for bus in data["single"]:
        if bus.get("pymodbus"):
            a, p = bus["asyncio"], bus["pymodbus"]
            lines.append(
                f"- {bus['baudrate']} baud, AsyncMaster / pymodbus AsyncModbusSerialClient: "
                f"transactions/s **{a['tps'] / p['tps']:.2f}x**, CPU per transaction "
                f"**{p['cpu_us'] / a['cpu_us']:.1f}x** less"
            )
    for bus in data["single"]:
        if bus.get("libmodbus"):
            lm, s_, a = bus["libmodbus"], bus["sync"], bus["asyncio"]
            lines.append(
                f"- {bus['baudrate']} baud, CPU per transaction against the libmodbus client "
                f"(C) on the same bus: Master **{s_['cpu_us'] / lm['cpu_us']:.2f}x**, "
                f"AsyncMaster **{a['cpu_us'] / lm['cpu_us']:.2f}x** "
                f"({lm['cpu_us']:.0f} µs for libmodbus)"
            )
    pty = data.get("pty")
    if pty:
        lines += [
            "",
            "### Pseudo-terminal pair, against the libmodbus server (bench/run_serial.py)",
            "",
            f"`{data.get('pty_note', '')}`: the pyrtu master's rate as a ratio of the",
            "libmodbus client's in the same cycles, and its CPU per transaction.",
            "",
            "| master | transactions/s | vs libmodbus client | client CPU µs/tx |",
            "|---|---:|---:|---:|",
        ]
        for key in pty:
            r = pty[key].get("pyrtu")
            if r:
                lines.append(
                    f"| pyrtu Master {key} | {r['tps']:,.0f} | **{r['vs_libmodbus']:.2f}** | "
                    f"{r['cpu_us']:.1f} |"
                )
    e = data.get("eight")
    if e:
        ratios = ", ".join(f"{r:.3f}" for r in e["ratios"])
        lines += [
            "",
            f"### {e['buses']} virtual buses at {e['baudrate']} baud, one AsyncMaster process",
            "",
            f"A simulated {e.get('drive', 'cfw100').upper()} on each bus (one `pyrtu simulate"
            f" {e.get('drive', 'cfw100')} --port ... --port ...` process serves the"
            f" {e['buses']}), each bus a `pyrtu vbus` process with its hub on the"
            f" {e.get('hub_loop', 'python').upper()} loop; {e['buses']} masters",
            "in one event loop poll FC 03 of 7 registers (19-byte answers; wire limit",
            f"1 / (27 characters + 2 x t3.5)) for {e['seconds']:.1f} s.",
            "",
            f"- per-bus ratio to the wire limit ({e['wire_limit']:.1f}/s): {ratios}; "
            f"minimum **{min(e['ratios']):.3f}**",
            f"- total {sum(e['tps']):.0f} transactions/s; the process's CPU: "
            f"{e['process_cpu_s']:.2f} s in {e['seconds']:.1f} s "
            f"(**{e['process_cpu_share'] * 100:.0f}% of one core**, "
            f"{e['cpu_us_per_tx']:.1f} µs per transaction); timeouts + frame errors: "
            f"{int(e['errors'])}",
            f"- with the drive's {e.get('response_delay_s', DRIVE_DELAY) * 1e3:g} ms response"
            f" delay the bus allows {e['limit_with_delay']:.1f}/s: "
            f"per-bus ratios {', '.join(f'{r:.3f}' for r in e['ratios_with_delay'])}",
            f"- the {e['buses']} hub processes used {e['hub_cpu_s_total']:.1f} s of CPU "
            f"({e['hub_cpu_s_total'] / e['seconds'] * 100:.0f}% of one core) in that time"
            + (
                f"; the drive simulators' process "
                f"{e['drive_cpu_s_total'] / e['seconds'] * 100:.0f}%"
                if "drive_cpu_s_total" in e
                else ""
            ),
        ]
        if "machine_busy_cores" in e:
            lines.append(
                f"- the whole machine (/proc/stat, the kernel's pty work included): "
                f"**{e['machine_busy_cores']:.2f} of {e['machine_cores']} cores busy**"
            )
    if data.get("notes"):
        lines += ["", "### Reading", ""]
        lines += [f"- {note}" for note in data["notes"]]
    lines += ["", END, ""]
    return "\n".join(lines)


def compare_hubs(rounds: int, seconds: float, buses: int, out: Path | None) -> None:
    """The 8-bus run with the hubs on the Python loop and on the C loop, interleaved."""
    print(f"load average before: {os.getloadavg()}")
    print(
        "| drive | hub loop | ratio to wire limit (min / median) | ratio to limit with"
        " delay (min) | tx/s total | AsyncMaster CPU | hubs CPU | drives CPU | errors |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    runs = []
    for _ in range(rounds):
        for drive_name in ("cfw100", "cv100"):
            for loop in ("python", "c"):
                e = eight_buses(115200, seconds, buses, drive_name, loop)
                runs.append(e)
                print(eight_line(e), flush=True)
    print(f"load average after: {os.getloadavg()}")
    if out is not None:
        out.write_text(json.dumps(runs, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--from-json", type=Path)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--only", choices=("single", "eight"))
    ap.add_argument("--buses", type=int, default=8)
    ap.add_argument("--drive", choices=sorted(DRIVES), default="cfw100")
    ap.add_argument(
        "--hubs",
        action="store_true",
        help="compare the hubs' loops: 8 buses on the Python loop and on the C loop,"
        " alternately, --rounds times per drive (cfw100 and cv100); prints table rows",
    )
    ap.add_argument("--baseline", help="a checkout of the code before, for a comparison")
    ap.add_argument(
        "--loops",
        action="store_true",
        help="--buses buses at 115200 under pyrtu.drivers.aio.run, asyncio.run and uvloop,"
        " interleaved --rounds times; prints table rows",
    )
    args = ap.parse_args()
    if args.loops:
        compare_loops(args.rounds, 3.0 if args.quick else 10.0, args.buses, args.drive, args.json)
        return
    if args.hubs:
        compare_hubs(args.rounds, 3.0 if args.quick else 10.0, args.buses, args.json)
        return
    if args.from_json:
        data = json.loads(args.from_json.read_text())
    else:
        import platform

        rounds = 1 if args.quick else args.rounds
        data = {
            "when": time.strftime("%Y-%m-%dT%H:%M:%S UTC", time.gmtime()),
            "machine": f"{os.cpu_count()} cores, Python {platform.python_version()}",
            "rounds": rounds,
            "single": [],
            "protocol_us": protocol_only(115200),
        }
        if args.baseline:
            rev = subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"],
                cwd=args.baseline,
                capture_output=True,
                text=True,
            ).stdout.strip()
            data["baseline_rev"] = rev
        if args.only != "eight":
            peers = build_peers(Path(tempfile.mkdtemp(prefix="pyrtu-peers-")))
            for baud, n in ((9600, 24), (115200, 160)):
                count = n // 2 if args.quick else n
                data["single"].append(
                    single_bus(baud, count, rounds, baud == 115200, args.baseline, peers)
                )
                print(json.dumps(data["single"][-1], indent=1), flush=True)
        if args.only != "single":
            data["eight"] = eight_buses(115200, 3.0 if args.quick else 10.0, args.buses, args.drive)
            print(json.dumps(data["eight"], indent=1), flush=True)
    if args.json:
        args.json.write_text(json.dumps(data, indent=1))
    text = section(data)
    print(text)


if __name__ == "__main__":
    main()
