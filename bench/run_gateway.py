"""Benchmark `pyrtu gateway` (issue 12); bench/report.py runs it for bench/RESULTS.md.

    python bench/run_gateway.py [--seconds S] [--json FILE]

Transactions per second through the gateway (a process of its own: ``pyrtu gateway``)
to a pyrtu slave (tests/peers/pyrtu_slave.py, the register pattern) and to a
simulated WEG CFW701 (``pyrtu simulate cfw701``), on a pseudo-terminal pair (socat,
``t35=0`` on both sides) and on the virtual bus at 115200 baud (``pyrtu vbus``, its
own process; specification timing), with 1, 4 and 16 concurrent TCP clients.  Each
client is one connection with one request in flight (`pyrtu.tcp.AsyncTcpClient`, all
in this process's event loop), every answer checked.  Wire efficiency = transactions/s
over the wire limit 1 / (request + response characters + 2 x t3.5).  CPU per
forwarded transaction: the gateway process's user+system time (/proc, 10 ms ticks)
over the transactions it forwarded.  pymodbus 3.16 offers no TCP-to-serial forwarder
(its remote datastore was removed in 3.x), so there is no pymodbus row.

The summary goes to stdout, the rows to ``--json``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from peers import pattern  # noqa: E402
from peers.tools import socat_pair  # noqa: E402

import pyrtu  # noqa: E402
from pyrtu import pdu  # noqa: E402
from pyrtu.drivers.aio import AsyncMaster  # noqa: E402
from pyrtu.drivers.aio import run as aio_run  # noqa: E402
from pyrtu.tcp import AsyncTcpClient  # noqa: E402

HEADING = "## Gateway: Modbus TCP to RTU (issue 12)"
BEGIN, END = "<!-- gateway:begin (bench/run_gateway.py) -->", "<!-- gateway:end -->"
BAUD = 115200
CLIENTS = (1, 4, 16)
#: what each target serves: (unit, address, count) of the FC 03 read
TARGETS = {"pyrtu slave": (1, 0, 10), "CFW701 sim": (1, 1, 7)}
#: the device's documented minimum response time past t3.5 (the WEG manuals: 2-10 ms;
#: the simulator answers after 2 ms): no master can make the wire go faster
DEVICE_DELAY = {"pyrtu slave": 0.0, "CFW701 sim": 0.002}


def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), e.get("PYTHONPATH", "")) if p)
    return e


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stop(proc: subprocess.Popen[str]) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out or ""


def spawn(argv: list[str], ready: str) -> tuple[subprocess.Popen[str], str]:
    """Start a program; (process, its first line, which must contain ``ready``)."""
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env()
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()
    if ready not in first:
        stop(proc)
        raise RuntimeError(f"{argv[:5]} did not start: {first!r}")
    return proc, first


@contextlib.contextmanager
def line(kind: str) -> Iterator[tuple[str, str, list[str]]]:
    """(gateway side, device side, timing options) of a pty pair or a virtual bus."""
    if kind == "pty":
        with socat_pair() as (a, b):
            yield a, b, ["--t35", "0"]
        return
    with tempfile.TemporaryDirectory() as d:
        bus = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", "vbus", "--drops", "2", "--baud", str(BAUD),
             "--parity", "N", "--dir", d],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env(),
        )  # fmt: skip
        assert bus.stdout is not None
        paths = [bus.stdout.readline().strip() for _ in range(2)]
        try:
            yield paths[0], paths[1], []
        finally:
            stop(bus)


def device(target: str, path: str, timing: list[str]) -> tuple[subprocess.Popen[str], str]:
    if target == "pyrtu slave":
        t35 = ["--t35", "0"] if timing else []
        return spawn(
            [sys.executable, str(ROOT / "tests/peers/pyrtu_slave.py"), path, "1",
             "--baud", str(BAUD), *t35],
            "READY",
        )  # fmt: skip
    return spawn(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw701", "--port", path, "--parity", "N",
         "--baudrate", str(BAUD), *timing, "--json"],
        "ready",
    )  # fmt: skip


@dataclass
class Row:
    line: str
    target: str
    clients: int
    transactions: int
    seconds: float
    tps: float
    wire_limit: float
    efficiency: float
    gateway_cpu_us: float
    errors: int


async def load(url: str, clients: int, seconds: float, target: str) -> tuple[int, int, float]:
    unit, address, count = TARGETS[target]
    request = pdu.read_request(pdu.READ_HOLDING_REGISTERS, address, count)
    expected = pattern.holdings(1, address, count) if target == "pyrtu slave" else None
    conns = [await AsyncTcpClient.connect(url, timeout=5.0) for _ in range(clients)]
    done = [0] * clients
    errors = [0]
    first = await conns[0].request(unit, request)  # the drive's values do not change here
    reference = pdu.parse_registers(first or b"", count) if expected is None else expected
    stop_at = time.monotonic() + seconds

    async def run(i: int) -> None:
        c = conns[i]
        while time.monotonic() < stop_at:
            try:
                got = await c.request(unit, request)
            except pyrtu.ModbusError:
                errors[0] += 1
                continue
            if pdu.parse_registers(got or b"", count) != reference:
                errors[0] += 1
            done[i] += 1

    t0 = time.monotonic()
    await asyncio.gather(*(run(i) for i in range(clients)))
    elapsed = time.monotonic() - t0
    for c in conns:
        await c.close()
    return sum(done), errors[0], elapsed


async def direct(
    path: str, timing: list[str], seconds: float, target: str
) -> tuple[int, float, float]:
    """The same reads by `pyrtu.drivers.aio.AsyncMaster` on the line itself, no gateway:
    (transactions, seconds, CPU seconds of this process)."""
    unit, address, count = TARGETS[target]
    t35 = 0.0 if timing else None
    async with AsyncMaster(path, BAUD, "N", t35=t35, timeout=0.5) as m:
        await m.read_holding_registers(unit, address, count)
        n = 0
        c0 = time.process_time()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            await m.read_holding_registers(unit, address, count)
            n += 1
        return n, time.monotonic() - t0, time.process_time() - c0


def tcp_side(seconds: float) -> list[tuple[int, float, float]]:
    """The TCP side alone: `pyrtu simulate cfw701 --tcp` is a TcpServer, the gateway's
    machinery with the drive in place of a bus.  (clients, transactions/s, server CPU
    µs per transaction)."""
    sim, ready = spawn(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw701", "--tcp", "127.0.0.1:0", "--json"],
        "ready",
    )
    out = []
    try:
        url = "tcp://" + json.loads(ready)["tcp"]
        for n in CLIENTS:
            cpu0 = cpu_seconds(sim.pid)
            total, errors, elapsed = asyncio.run(load(url, n, seconds, "CFW701 sim"))
            cpu = cpu_seconds(sim.pid) - cpu0
            assert errors == 0
            out.append((n, round(total / elapsed, 1), round(cpu / max(total, 1) * 1e6, 1)))
            print(out[-1], flush=True)
    finally:
        stop(sim)
    return out


def wire_limit(kind: str, count: int) -> float:
    t = pyrtu.char_timing(BAUD, "N")
    chars = 8 + 5 + 2 * count
    gap = 0.0 if kind == "pty" else 2 * t.t35
    return float(1.0 / (chars * t.char + gap))


def measure(seconds: float) -> list[Row]:
    rows: list[Row] = []
    for kind in ("pty", "vbus"):
        for target in TARGETS:
            with line(kind) as (gw_side, dev_side, timing):
                dev, _ = device(target, dev_side, timing)
                limit = wire_limit(kind, TARGETS[target][2])
                n, elapsed, cpu = aio_run(direct(gw_side, timing, seconds, target))
                rows.append(
                    Row(kind, target, 0, n, round(elapsed, 3), round(n / elapsed, 1),
                        round(limit, 1), round(n / elapsed / limit, 3),
                        round(cpu / max(n, 1) * 1e6, 1), 0)
                )  # fmt: skip
                print(rows[-1], flush=True)
                gw, ready = spawn(
                    [sys.executable, "-m", "pyrtu", "gateway", "--listen", "127.0.0.1:0",
                     "--port", f"{gw_side}=1", "--baudrate", str(BAUD), "--parity", "N",
                     "--timeout", "0.5", "--json", *timing],
                    "ready",
                )  # fmt: skip
                try:
                    url = "tcp://" + json.loads(ready)["listen"]
                    for n in CLIENTS:
                        cpu0 = cpu_seconds(gw.pid)
                        total, errors, elapsed = asyncio.run(load(url, n, seconds, target))
                        cpu = cpu_seconds(gw.pid) - cpu0
                        tps = total / elapsed
                        rows.append(
                            Row(kind, target, n, total, round(elapsed, 3), round(tps, 1),
                                round(limit, 1), round(tps / limit, 3),
                                round(cpu / max(total, 1) * 1e6, 1), errors)
                        )  # fmt: skip
                        print(rows[-1], flush=True)
                finally:
                    stop(gw)
                    stop(dev)
    return rows


def cpu_model() -> str:
    with contextlib.suppress(OSError), open("/proc/cpuinfo", encoding="ascii") as f:
        for text in f:
            if text.startswith("model name"):
                return text.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def section(
    rows: list[Row], seconds: float, tcp: list[tuple[int, float, float]] | None = None
) -> str:
    when = time.strftime("%Y-%m-%dT%H:%M:%S UTC", time.gmtime())
    load = os.getloadavg()[0]
    out = [
        BEGIN,
        HEADING,
        "",
        f"`python bench/run_gateway.py --seconds {seconds:g}`, one run, {when}.  "
        f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"pyrtu backend `{pyrtu.BACKEND}`; load average {load:.1f} at the end (the machine "
        "was shared with other jobs: compare the ratios to the direct rows of the same run).",
        "",
        "FC 03 through `pyrtu gateway` (its own process) onto one bus at 115200 baud: "
        "10 registers from the pyrtu slave (tests/peers/pyrtu_slave.py), 7 (P001-P007) "
        "from the simulated CFW701 (`pyrtu simulate cfw701`: its manual's response delay "
        "included).  N clients = N TCP connections, one request in flight each, every "
        "answer checked (errors: 0 in every row unless shown).  Pseudo-terminal pair: socat, "
        "`t35=0` on both sides; virtual bus: `pyrtu vbus`, specification timing (t3.5 = "
        "1750 µs), wire limit = 1 / (request + response characters + 2 x t3.5).  Gateway "
        "CPU: its process's user+system time over the transactions forwarded.  Clients 0: "
        "the same reads by `pyrtu.drivers.aio.AsyncMaster` on the line directly (no gateway, no "
        "TCP; its CPU in the last column), the reference for the gateway's own cost.",
        "",
        "| line | device | clients | transactions/s | wire limit /s | efficiency "
        "| gateway CPU µs/tx | errors |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        limit = f"{r.wire_limit:,.0f}" if r.line == "vbus" else "-"
        eff = f"**{r.efficiency:.3f}**" if r.line == "vbus" else "-"
        who = "direct" if r.clients == 0 else str(r.clients)
        out.append(
            f"| {r.line} | {r.target} | {who} | {r.tps:,.0f} | {limit} | {eff} "
            f"| {r.gateway_cpu_us:.1f} | {r.errors} |"
        )
    vbus4 = [r for r in rows if r.line == "vbus" and r.clients == 4]
    if tcp:
        out += [
            "",
            "The TCP side alone (`pyrtu simulate cfw701 --tcp`: `TcpServer`, the gateway's "
            "listener, framer and queue with the drive in place of a bus):",
            "",
            "| clients | transactions/s | server CPU µs/tx |",
            "|---:|---:|---:|",
            *(f"| {n} | {tps:,.0f} | {cpu:.1f} |" for n, tps, cpu in tcp),
        ]
    out += ["", "Ratios and targets (same run):", ""]
    for r in vbus4:
        met = "met" if r.efficiency >= 0.95 else "NOT met"
        line_ = (
            f"- wire efficiency on the virtual bus, 4 clients, {r.target}: "
            f"**{r.efficiency:.3f}** (target >= 0.95: {met})"
        )
        delay = DEVICE_DELAY[r.target]
        if delay:
            allowed = 1.0 / (1.0 / r.wire_limit + delay)
            line_ += (
                f"; against what the drive's documented {delay * 1e3:.0f} ms response time "
                f"allows ({allowed:.1f}/s): **{r.tps / allowed:.3f}**"
            )
        out.append(line_)
    for kind in ("pty", "vbus"):
        for target in TARGETS:
            base = next(r for r in rows if (r.line, r.target, r.clients) == (kind, target, 0))
            for n in CLIENTS:
                r = next(r for r in rows if (r.line, r.target, r.clients) == (kind, target, n))
                out.append(
                    f"- {kind}, {target}, {n} client{'s' if n > 1 else ''}: gateway / direct "
                    f"AsyncMaster = {r.tps / base.tps:.2f}x transactions/s; gateway CPU "
                    f"{r.gateway_cpu_us:.0f} µs/tx against {base.gateway_cpu_us:.0f} µs/tx"
                )
    for target in TARGETS:
        one = next(r for r in rows if r.line == "pty" and r.target == target and r.clients == 1)
        many = next(r for r in rows if r.line == "pty" and r.target == target and r.clients == 16)
        out.append(
            f"- pty, {target}: 16 clients / 1 client = {many.tps / one.tps:.2f}x "
            "(one transaction at a time on the bus; more clients only keep the queue full)"
        )
    out += [
        "- the same clients direct to a pymodbus serial server through a pymodbus forwarder: "
        "not measured; pymodbus 3.16.1 has no forwarder (no remote datastore).",
        "",
        *reading(rows, load),
        "",
        END,
    ]
    return "\n".join(out) + "\n"


def reading(rows: list[Row], load: float) -> list[str]:
    """How to read the run: the gateway against the direct master of the same minute."""

    def ratios(kind: str) -> str:
        parts = []
        for target in TARGETS:
            base = next(r for r in rows if (r.line, r.target, r.clients) == (kind, target, 0))
            got = [r.tps / base.tps for r in rows if (r.line, r.target) == (kind, target)
                   and r.clients]  # fmt: skip
            parts.append(f"{min(got):.2f}-{max(got):.2f}x ({target})")
        return ", ".join(parts)

    direct = next(r for r in rows if (r.line, r.target, r.clients) == ("vbus", "pyrtu slave", 0))
    base_cpu = {(r.line, r.target): r.gateway_cpu_us for r in rows if r.clients == 0}
    extra = [r.gateway_cpu_us - base_cpu[r.line, r.target] for r in rows if r.clients]
    extra.sort()
    return [
        f"Reading this run: load average {load:.1f} on {os.cpu_count()} cores; the direct "
        f"AsyncMaster reached {direct.efficiency:.3f} of the wire limit on the virtual bus "
        "with the pyrtu slave (the gateway cannot beat the master it drives).  The gateway "
        "against the direct "
        f"master on the same line in the same minute: {ratios('vbus')} on the virtual bus, "
        f"{ratios('pty')} on the pty pair, and a median of {extra[len(extra) // 2]:.0f} µs "
        "of CPU per forwarded transaction over the direct master's (TCP receive, MBAP "
        "framing, the queue, TCP send).",
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="per measurement")
    parser.add_argument(
        "--no-write",
        action="store_true",
        help="accepted and ignored: RESULTS.md is written by bench/report.py only",
    )
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")
    args = parser.parse_args()
    rows = measure(args.seconds)
    tcp = tcp_side(args.seconds)
    if args.json:
        args.json.write_text(json.dumps({"rows": [asdict(r) for r in rows], "tcp": tcp}))
    text = section(rows, args.seconds, tcp)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
