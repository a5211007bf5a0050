"""Master/slave over serial (issue 4): FC 03 of 10 registers, one transaction at a time.

Part 1, a pseudo-terminal pair (socat ``pty,raw,echo=0`` both sides; no wire, so
pyrtu runs with ``t35=0`` on both sides and libmodbus does not wait either).
Clients: the pyrtu master (C framer, and "pyrtu-python" on the pure-Python
framer), pymodbus, minimalmodbus and the libmodbus client;
servers: the pyrtu slave (its own process) and the libmodbus server.  Every answer
is checked against the pattern of tests/peers/pattern.py.

Part 2, the virtual bus (pyrtu.vbus) at 9600 and 115200 baud 8N1, with the
specification's timing on both sides: the pyrtu master against the pyrtu slave,
compared with the wire limit ``1 / (33 * char_time + 2 * t3.5)`` (an 8-byte
request and a 25-byte response, each preceded by a t3.5 silence).

Each benchmark round is ``ROUND`` transactions; pytest-benchmark times the rounds,
``extra_info`` has the medians per transaction.  CPU time per transaction is the
client's (its thread for the Python clients, its process for the C client) and
the server process's (from /proc, 10 ms resolution, over the whole benchmark).
Run ``python bench/run_serial.py`` to run this and write the section of
bench/RESULTS.md.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import peers.pattern as pattern
from peers.tools import (
    Peer,
    PeerBinaries,
    libmodbus_bench,
    libmodbus_server,
    minimal_instrument,
    pymodbus_client,
    pyrtu_slave_process,
    socat_pair,
)

from pyrtu.drivers.master import Master
from pyrtu.vbus import VirtualBus

pytest_plugins = ["peers.fixtures"]

SLAVE = 7
ADDRESS = 0
COUNT = 10
EXPECTED = pattern.holdings(SLAVE, ADDRESS, COUNT)
#: cycles per server (a cycle: one round of every client, in turn)
CYCLES = 11
WARMUP = 50
#: transactions per round, per client (a round lasts about 0.2-0.5 s)
ROUND = {
    "pyrtu": 2000,
    "pyrtu-python": 1500,
    "libmodbus": 2500,
    "pymodbus": 200,
    "minimalmodbus": 200,
}
#: "pyrtu-python": the same master on the pure-Python framer (backend="python")
CLIENTS = ("pyrtu", "pyrtu-python", "libmodbus", "pymodbus", "minimalmodbus")
SERVERS = ("pyrtu", "libmodbus")
VBUS_BAUDS = (9600, 115200)
VBUS_ROUND = {9600: 24, 115200: 150}


def wire_limit(baudrate: int, bits: int = 10) -> float:
    """Transactions per second the wire allows: 33 characters and two t3.5 silences."""
    char = bits / baudrate
    t35 = 3.5 * char if baudrate <= 19200 else 0.00175
    return 1.0 / (33 * char + 2 * t35)


def start_server(stack: ExitStack, name: str, port: str, binaries: PeerBinaries) -> Peer:
    if name == "pyrtu":
        return stack.enter_context(pyrtu_slave_process(port, SLAVE, t35=0.0))
    return stack.enter_context(libmodbus_server(binaries, port, SLAVE))


def python_client(stack: ExitStack, name: str, port: str) -> Callable[[], list[int]]:
    """One FC 03 transaction of the named Python client, as a callable."""
    if name.startswith("pyrtu"):
        backend = "python" if name == "pyrtu-python" else "c"
        # the clients of one run share the port and take turns: no exclusive lock
        master = Master(
            port, 115200, parity="N", timeout=1.0, t35=0, backend=backend, exclusive=False
        )
        stack.callback(master.close)
        return lambda: master.read_holding_registers(SLAVE, ADDRESS, COUNT)
    if name == "pymodbus":
        client = pymodbus_client(port)
        stack.callback(client.close)

        def pymodbus_read() -> list[int]:
            rr = client.read_holding_registers(ADDRESS, count=COUNT, device_id=SLAVE)
            return list(rr.registers)

        return pymodbus_read
    inst = minimal_instrument(port, SLAVE)
    stack.callback(inst.serial.close)
    return lambda: list(inst.read_registers(ADDRESS, COUNT))


@pytest.fixture(scope="module")
def binaries(peer_binaries: PeerBinaries) -> PeerBinaries:
    return peer_binaries


def record(
    benchmark: Any,
    *,
    transactions: int,
    walls: list[float],
    cpus: list[float],
    server_cpu: float | None,
    total: int,
) -> None:
    """Medians per transaction into extra_info (the numbers RESULTS.md quotes)."""
    benchmark.extra_info.update(summarize(transactions, walls, cpus, server_cpu, total))


def summarize(
    transactions: int, walls: list[float], cpus: list[float], server_cpu: float | None, total: int
) -> dict[str, Any]:
    wall = statistics.median(walls) / transactions
    return {
        "transactions_per_round": transactions,
        "rounds": len(walls),
        "tps": 1.0 / wall,
        "tps_min": transactions / max(walls),
        "tps_max": transactions / min(walls),
        "us_per_tx": wall * 1e6,
        "client_cpu_us_per_tx": statistics.median(cpus) / transactions * 1e6,
        "server_cpu_us_per_tx": None if server_cpu is None else server_cpu / total * 1e6,
    }


class Round:
    """One client's rounds against the server: wall and CPU times per round."""

    def __init__(self, name: str, run: Callable[[], tuple[float, float]], peer: Peer) -> None:
        self.name = name
        self.run = run
        self.peer = peer
        self.walls: list[float] = []
        self.cpus: list[float] = []
        self.server_cpu = 0.0

    def __call__(self) -> None:
        s0 = self.peer.cpu_seconds()
        wall, cpu = self.run()
        self.server_cpu += self.peer.cpu_seconds() - s0
        self.walls.append(wall)
        self.cpus.append(cpu)


@pytest.mark.benchmark(group="FC 03 x 10 registers over a pty pair (socat), all clients in turn")
@pytest.mark.parametrize("server", SERVERS)
def test_pty(benchmark: Any, binaries: PeerBinaries, server: str) -> None:
    """Every client against one server, interleaved: a benchmark round is a cycle of
    one round per client, so all clients are measured in the same stretch of time.

    The machine is shared and its speed drifts (rounds of one pair vary by tens of
    percent): each client's *vs libmodbus client* figure is the median over the
    cycles of its rate divided by the libmodbus client's rate in the same cycle.
    pytest-benchmark's own time is the cycle's; the figures are in extra_info.
    """
    rounds: dict[str, Round] = {}
    with ExitStack() as stack:
        a, b = stack.enter_context(socat_pair())
        peer = start_server(stack, server, b, binaries)
        libmodbus_bench(binaries, a, SLAVE, WARMUP)  # the server's first answers
        for client in CLIENTS:
            n = ROUND[client]
            if client == "libmodbus":

                def run_c(n: int = n) -> tuple[float, float]:
                    report = libmodbus_bench(binaries, a, SLAVE, n, address=ADDRESS, warmup=10)
                    assert report["errors"] == 0 and report["wrong"] == 0, report
                    return report["seconds"], report["cpu_seconds"]  # its own clocks

                rounds[client] = Round(client, run_c, peer)
                continue
            transaction = python_client(stack, client, a)
            for _ in range(WARMUP):
                assert transaction() == EXPECTED

            def run_py(
                n: int = n, transaction: Callable[[], list[int]] = transaction, client: str = client
            ) -> tuple[float, float]:
                c0, t0 = time.thread_time(), time.perf_counter()
                for _ in range(n):
                    if transaction() != EXPECTED:
                        raise AssertionError(f"{client} read a wrong value from {server}")
                return time.perf_counter() - t0, time.thread_time() - c0

            rounds[client] = Round(client, run_py, peer)

        def cycle() -> None:
            for r in rounds.values():
                r()

        benchmark.pedantic(cycle, rounds=CYCLES, iterations=1, warmup_rounds=0)
    anchor = rounds["libmodbus"]
    out: dict[str, Any] = {}
    for client, r in rounds.items():
        n = ROUND[client]
        info = summarize(n, r.walls, r.cpus, r.server_cpu, n * CYCLES)
        ratios = [
            (n / w) / (ROUND["libmodbus"] / ref)
            for w, ref in zip(r.walls, anchor.walls, strict=True)
        ]
        info["vs_libmodbus_client"] = statistics.median(ratios)
        out[client] = info
    benchmark.extra_info.update(server=server, path="socat pty pair", clients=out)


@pytest.fixture
def vbus_pair(request: pytest.FixtureRequest) -> Iterator[tuple[VirtualBus, Peer]]:
    baudrate: int = request.param
    with VirtualBus(2, baudrate=baudrate, parity="N") as bus, ExitStack() as stack:
        peer = stack.enter_context(pyrtu_slave_process(bus.paths[1], SLAVE, baudrate=baudrate))
        assert bus.wait_clients(1)
        yield bus, peer


@pytest.mark.benchmark(group="FC 03 x 10 registers on the virtual bus, spec timing")
@pytest.mark.parametrize("vbus_pair", VBUS_BAUDS, indirect=True, ids=lambda b: f"{b}baud")
def test_vbus(benchmark: Any, vbus_pair: tuple[VirtualBus, Peer]) -> None:
    bus, peer = vbus_pair
    n = VBUS_ROUND[bus.baudrate]
    walls: list[float] = []
    cpus: list[float] = []
    with Master(bus.paths[0], bus.baudrate, parity="N", timeout=1.0) as master:
        for _ in range(5):
            assert master.read_holding_registers(SLAVE, ADDRESS, COUNT) == EXPECTED
        cpu0 = peer.cpu_seconds()

        def run() -> None:
            c0, t0 = time.thread_time(), time.perf_counter()
            for _ in range(n):
                if master.read_holding_registers(SLAVE, ADDRESS, COUNT) != EXPECTED:
                    raise AssertionError("wrong value on the virtual bus")
            walls.append(time.perf_counter() - t0)
            cpus.append(time.thread_time() - c0)

        benchmark.pedantic(run, rounds=5, iterations=1, warmup_rounds=0)
        server_cpu = peer.cpu_seconds() - cpu0
        t35 = master.t35
    limit = wire_limit(bus.baudrate)
    benchmark.extra_info.update(
        client="pyrtu",
        server="pyrtu",
        path=f"virtual bus {bus.baudrate} baud 8N1",
        baudrate=bus.baudrate,
        char_time_us=bus.char_time * 1e6,
        t35_us=t35 * 1e6,
        wire_limit_tps=limit,
    )
    record(
        benchmark,
        transactions=n,
        walls=walls,
        cpus=cpus,
        server_cpu=server_cpu,
        total=n * 5,
    )
    benchmark.extra_info["ratio_to_wire"] = benchmark.extra_info["tps"] / limit
