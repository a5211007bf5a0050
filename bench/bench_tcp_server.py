"""The Modbus TCP servers: CPU per answered read of pyrtu's ``TcpServer`` against
libmodbus's C server and pymodbus's server, one client, one run (issue 30).

    python -m pytest bench/bench_tcp_server.py -p no:cacheprovider [--benchmark-json=out.json]
    (TCP_SERVER_N=20000: reads per round)

The client is libmodbus's C client (tests/peers/libmodbus_client.c's ``bench``: N
``modbus_read_registers`` of 10 holding registers, unit 1, address 0, each answer
compared with the register pattern of tests/peers/pattern.py), against each server
in turn, each in a process of its own on a free 127.0.0.1 port:

* ``libmodbus``: tests/peers/libmodbus_server.c (``modbus_receive`` /
  ``modbus_reply``, one connection at a time), as the master benchmarks use;
* ``pyrtu``: ``TcpServer.for_store`` (pyrtu.tcp.server) on the C core (its engine
  answers the reads in C, no Python per request), serving a
  DataStore of the pattern (bench/run_tcp_server.py ``pyrtu``);
* ``pymodbus``: pymodbus's asyncio ``ModbusTcpServer`` serving the same tables
  (bench/run_tcp_server.py ``pymodbus``); both Python servers on asyncio's default
  event loop;
* ``asyncio floor``: not a Modbus server, the floor under any server on an asyncio
  event loop: a bare ``asyncio.Protocol`` writing the one answer, built once, for
  the benchmark's one request (bench/run_tcp_server.py ``floor``).  What it costs is
  the event loop's and the kernel's alone: a server that enters Python per request
  cannot cost less.

Per server: one untimed client run of WARMUP reads, then 5 rounds, each one client
run of N reads (its own connection; ``--warmup 0``).  The figure is the server
process's CPU over the client's run divided by N: user + system time of the whole
process (every thread, dead ones too), read from the kernel's per-process CPU clock
(``clock_gettime`` on the clock ``clock_getcpuclockid(pid)`` names, nanoseconds,
the same account as utime + stime of /proc/<pid>/stat, whose 10 ms ticks would be
too coarse for libmodbus's few µs a read: those are kept beside it as
``proc_stat_cpu_us_per_tx``).  The round counts only if the client saw N answers,
every one of them right (its ``errors`` and ``wrong`` are 0), so a server answering
exceptions cannot look fast; pyrtu's server's own counters (answers, exceptions)
are checked at the end too.  The connect and close of each round are the server's
cost as well (one of each per N reads).

pytest-benchmark's own statistics are the wall time of a round; the figures that
count are in each row's ``extra_info``: ``cpu_us_per_tx`` (the server's, one per
round), ``tps`` and ``client_cpu_us_per_tx``.  bench/report.py keeps the JSON and
RESULTS.md gives the medians and the ratios to libmodbus's server and to
pymodbus's (targets for ``TcpServer``: <= 2x and <= 0.25x).  Measurements, not
tests: nothing is asserted about speed.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from peers.tools import (  # noqa: E402
    Peer,
    PeerBinaries,
    build_peers,
    free_tcp_port,
    libmodbus_bench,
    libmodbus_server,
)

N = int(os.environ.get("TCP_SERVER_N", "20000"))
ROUNDS = 5
WARMUP = 300
UNIT = 1
GROUP = "tcp server: FC 03, 10 registers, libmodbus client"
#: CPUCLOCK_SCHED of Linux's process CPU clocks (include/linux/posix-timers.h)
_CPUCLOCK_SCHED = 2


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (all its threads), to the nanosecond:
    the clock ``clock_getcpuclockid(pid)`` returns, ``MAKE_PROCESS_CPUCLOCK(pid,
    CPUCLOCK_SCHED)`` in Linux's terms."""
    return time.clock_gettime((~pid << 3) | _CPUCLOCK_SCHED)


@pytest.fixture(scope="module")
def binaries(tmp_path_factory: pytest.TempPathFactory) -> PeerBinaries:
    return build_peers(tmp_path_factory.mktemp("tcp-server-peers"))


def _server(binaries: PeerBinaries, name: str, port: int) -> Peer:
    if name == "libmodbus":
        return libmodbus_server(binaries, f"tcp:127.0.0.1:{port}", UNIT)
    runner = ROOT / "bench" / "run_tcp_server.py"
    argv = [sys.executable, str(runner), name, "--unit", str(UNIT), "--port", str(port)]
    return Peer(f"{name}-tcp-server", argv)


@pytest.fixture(params=["libmodbus", "pyrtu", "pymodbus", "floor"])
def server(request: pytest.FixtureRequest, binaries: PeerBinaries) -> Iterator[tuple[Peer, int]]:
    """The server ``request.param`` started on a free port: (its peer, the port)."""
    port = free_tcp_port()
    with _server(binaries, str(request.param), port) as peer:
        yield peer, port


def test_server(benchmark: Any, binaries: PeerBinaries, server: tuple[Peer, int]) -> None:
    peer, port = server
    device = f"tcp:127.0.0.1:{port}"

    def client(n: int) -> dict[str, Any]:
        r: dict[str, Any] = libmodbus_bench(binaries, device, UNIT, n, warmup=0)
        assert r["transactions"] == n and r["errors"] == 0 and r["wrong"] == 0, r
        return r

    client(WARMUP)
    cpu: list[float] = []
    ticks: list[float] = []
    tps: list[float] = []
    client_cpu: list[float] = []

    def run() -> None:
        c0, s0 = process_cpu_seconds(peer.pid), peer.cpu_seconds()
        r = client(N)
        c1, s1 = process_cpu_seconds(peer.pid), peer.cpu_seconds()
        cpu.append((c1 - c0) / N * 1e6)
        ticks.append((s1 - s0) / N * 1e6)
        tps.append(float(r["tps"]))
        client_cpu.append(float(r["cpu_us_per_tx"]))

    benchmark.group = GROUP
    benchmark.pedantic(run, rounds=ROUNDS, iterations=1, warmup_rounds=0)
    assert peer.alive(), peer.log_tail()
    stats = peer.stop()
    benchmark.extra_info.update(
        transactions=N,
        cpu_us_per_tx=cpu,
        proc_stat_cpu_us_per_tx=ticks,
        tps=tps,
        client_cpu_us_per_tx=client_cpu,
        server=peer.ready_line,
        server_stats=stats,
    )
    if peer.name.startswith(("pyrtu", "floor")):
        counters = dict(kv.split("=") for kv in stats.split())
        assert counters.get("exceptions", "0") == "0", stats
        assert int(counters["answers"]) == WARMUP + ROUNDS * N, stats
