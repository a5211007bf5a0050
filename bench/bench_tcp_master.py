"""The sync Modbus TCP master: CPU per transaction of ``Master("tcp://...")`` against
libmodbus's C client and pymodbus's sync client, one server, one run (issue 30.1).

    python -m pytest bench/bench_tcp_master.py -p no:cacheprovider [--benchmark-json=out.json]
    (TCP_MASTER_N=20000: transactions per round)

The server is libmodbus's (tests/peers/libmodbus_server.c, the C server of the
issue's table: one connection at a time, each client connects in turn), on
127.0.0.1.  Every client reads 10 holding registers (FC 03) of unit 1 from address 0,
TCP_MASTER_N times per round, each answer checked against the register pattern:

* ``libmodbus``: tests/peers/libmodbus_client.c's ``bench`` (``modbus_read_registers``
  in a loop; its own CPU time, CLOCK_PROCESS_CPUTIME_ID, over the loop);
* ``pyrtu c``: ``Master("tcp://...").read_holding_registers`` on the C core (the
  transaction one call of csrc/rtu_tcp_io.c, the GIL released);
* ``pyrtu twin``: the same with ``backend="python"`` (pyrtu/drivers/_pyxfer.py);
* ``pymodbus``: pymodbus's ``ModbusTcpClient.read_holding_registers``;
* ``c transaction alone``: the floor under ``pyrtu c``, its transaction's one C
  call (`pyrtu.drivers.xfer.TcpXferRunner.call`) in a loop, nothing else.

For the Python clients CPU is this process's (``time.process_time``) over the loop.
pytest-benchmark's own statistics are the wall time of a round; the figures that
count are in each row's ``extra_info``: ``cpu_us_per_tx`` (one per round) and
``tps``.  bench/report.py keeps the JSON and RESULTS.md gives the medians and the
ratios to libmodbus's client and to pymodbus's (targets: <= 1.5x and <= 0.5x).
Measurements, not tests: nothing is asserted about speed.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from peers import pattern  # noqa: E402
from peers.tools import (  # noqa: E402
    PeerBinaries,
    build_peers,
    free_tcp_port,
    libmodbus_bench,
    libmodbus_server,
)

from pyrtu import Master  # noqa: E402

N = int(os.environ.get("TCP_MASTER_N", "20000"))
ROUNDS = 5
WARMUP = 300
UNIT, ADDRESS, COUNT = 1, 0, 10
EXPECTED = pattern.holdings(UNIT, ADDRESS, COUNT)
GROUP = "tcp master: FC 03, 10 registers"


@pytest.fixture(scope="module")
def binaries(tmp_path_factory: pytest.TempPathFactory) -> PeerBinaries:
    return build_peers(tmp_path_factory.mktemp("tcp-master-peers"))


@pytest.fixture(scope="module")
def server(binaries: PeerBinaries) -> Iterator[tuple[str, int]]:
    """libmodbus's TCP server on a free port: (host, port)."""
    port = free_tcp_port()
    with libmodbus_server(binaries, f"tcp:127.0.0.1:{port}", UNIT):
        yield "127.0.0.1", port


def _rounds(benchmark: Any, one_round: Callable[[], tuple[float, float]]) -> None:
    """``one_round() -> (cpu seconds, wall seconds)`` of N transactions, ROUNDS times."""
    cpu: list[float] = []
    tps: list[float] = []

    def run() -> None:
        c, w = one_round()
        cpu.append(c / N * 1e6)
        tps.append(N / w)

    benchmark.group = GROUP
    benchmark.pedantic(run, rounds=ROUNDS, iterations=1, warmup_rounds=0)
    benchmark.extra_info.update(transactions=N, cpu_us_per_tx=cpu, tps=tps)


def _timed(read: Callable[[], Any]) -> tuple[float, float]:
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(N):
        read()
    return time.process_time() - c0, time.perf_counter() - w0


def test_libmodbus(benchmark: Any, binaries: PeerBinaries, server: tuple[str, int]) -> None:
    host, port = server

    def one_round() -> tuple[float, float]:
        r = libmodbus_bench(binaries, f"tcp:{host}:{port}", UNIT, N, warmup=WARMUP)
        assert r["errors"] == 0 and r["wrong"] == 0, r
        return float(r["cpu_seconds"]), float(r["seconds"])

    _rounds(benchmark, one_round)


@pytest.mark.parametrize("backend", ["c", "python"], ids=["pyrtu c", "pyrtu twin"])
def test_pyrtu(benchmark: Any, server: tuple[str, int], backend: str) -> None:
    import pyrtu

    if backend not in pyrtu.available_backends():
        pytest.skip(f"the {backend} backend is not available")
    host, port = server
    with Master(f"tcp://{host}:{port}", timeout=2.0, backend=backend) as m:
        for _ in range(WARMUP):
            assert m.read_holding_registers(UNIT, ADDRESS, COUNT) == EXPECTED

        def read() -> None:
            m.read_holding_registers(UNIT, ADDRESS, COUNT)

        _rounds(benchmark, lambda: _timed(read))
        assert m.read_holding_registers(UNIT, ADDRESS, COUNT) == EXPECTED
        assert m.counters["responses"] == WARMUP + ROUNDS * N + 1


def test_c_transaction_alone(benchmark: Any, server: tuple[str, int]) -> None:
    """The floor under ``pyrtu c``: the transaction's one C call alone (send, wait,
    read the whole answer: csrc/rtu_tcp_io.c's three system calls, the GIL released),
    the same request each time, no Python around it but the call: what any client
    on this machine pays for a transaction over the loopback."""
    import pyrtu
    from pyrtu.tcp import TcpClient

    if "c" not in pyrtu.available_backends():
        pytest.skip("the c backend is not available")
    host, port = server
    with TcpClient(f"tcp://{host}:{port}", timeout=2.0, backend="c") as client:
        runner = client._runner
        body = bytes((3, 0, ADDRESS, 0, COUNT))
        call = runner.call
        expected = (1 + 1 + 2 * COUNT) << 8  # (the answer's PDU length; status: answered)
        for _ in range(WARMUP):
            assert call(1, UNIT, body, True, 2.0) == expected

        def read() -> None:
            call(1, UNIT, body, True, 2.0)

        _rounds(benchmark, lambda: _timed(read))
        assert call(1, UNIT, body, True, 2.0) == expected


def test_pymodbus(benchmark: Any, server: tuple[str, int]) -> None:
    from pymodbus.client import ModbusTcpClient

    host, port = server
    client = ModbusTcpClient(host, port=port, timeout=2.0)
    assert client.connect()
    try:
        for _ in range(WARMUP):
            r = client.read_holding_registers(ADDRESS, count=COUNT, device_id=UNIT)
            assert r.registers == EXPECTED

        def read() -> None:
            client.read_holding_registers(ADDRESS, count=COUNT, device_id=UNIT)

        _rounds(benchmark, lambda: _timed(read))
    finally:
        client.close()
