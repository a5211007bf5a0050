"""The asyncio Modbus TCP master: CPU per transaction of ``AsyncMaster("tcp://...")``
against libmodbus's C client and pymodbus's ``AsyncModbusTcpClient``, one server,
one run (issue 30.1).

    python -m pytest bench/bench_tcp_async.py -p no:cacheprovider [--benchmark-json=out.json]
    (TCP_MASTER_N=20000: transactions per round)

The server is libmodbus's (tests/peers/libmodbus_server.c, as in
bench/bench_tcp_master.py), on 127.0.0.1; every client reads 10 holding registers
(FC 03) of unit 1 from address 0, TCP_MASTER_N times per round:

* ``libmodbus``: tests/peers/libmodbus_client.c's ``bench`` (its own CPU time);
* ``pyrtu async c``: ``await AsyncMaster("tcp://...").read_holding_registers``, one
  request at a time (``max_in_flight=1``, the default), on the C core (a read holding
  one whole answer to the one request in flight is taken by its MBAP header; any
  other read is scanned by rtu_tcp_scan);
* ``pyrtu async twin``: the same with ``backend="python"`` (the twin's scan: so only
  the reads the header alone does not settle differ from the C core's);
* ``pyrtu async 8 in flight``: the C core with ``max_in_flight=8``, the reads
  awaited 8 at a time (``asyncio.gather``; libmodbus's server answers pipelined
  requests in order, but its accepted socket keeps Nagle's algorithm on, so each
  batch's later answers wait for the client's delayed ACK: about 40 ms a batch;
  this row reads N / 25 per round to keep the run short, CPU still per transaction);
* ``pymodbus async``: ``await AsyncModbusTcpClient.read_holding_registers``;
* ``asyncio floor``: not a Modbus client, the floor under any client that awaits
  each answer on an asyncio event loop: a bare ``asyncio.Protocol`` writing the
  request (built once with ``struct``, its transaction id counted) and a future
  resolved in ``data_received`` once the whole answer is in, the answer compared
  with the one the pattern gives.  What it costs is the event loop's and the
  kernel's alone.

Every asyncio client runs on asyncio's default event loop (``asyncio.new_event_loop``),
one loop per client; CPU is this process's (``time.process_time``) over the
round.  The figures are in each row's ``extra_info`` (``cpu_us_per_tx``, ``tps``);
RESULTS.md gives the medians and the ratios to libmodbus's client and to pymodbus's
async one (targets for one request at a time: <= 3x and <= 0.5x).  Measurements,
not tests: nothing is asserted about speed.
"""

from __future__ import annotations

import asyncio
import os
import struct
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
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

from pyrtu.drivers.aio import AsyncMaster  # noqa: E402

N = int(os.environ.get("TCP_MASTER_N", "20000"))
ROUNDS = 5
WARMUP = 300
PIPELINE = 8
PIPELINED_N = max(PIPELINE, N // 25 // PIPELINE * PIPELINE)  # (see the module docstring)
UNIT, ADDRESS, COUNT = 1, 0, 10
EXPECTED = pattern.holdings(UNIT, ADDRESS, COUNT)
GROUP = "tcp async master: FC 03, 10 registers"


@pytest.fixture(scope="module")
def binaries(tmp_path_factory: pytest.TempPathFactory) -> PeerBinaries:
    return build_peers(tmp_path_factory.mktemp("tcp-async-peers"))


@pytest.fixture(scope="module")
def server(binaries: PeerBinaries) -> Iterator[tuple[str, int]]:
    """libmodbus's TCP server on a free port: (host, port)."""
    port = free_tcp_port()
    with libmodbus_server(binaries, f"tcp:127.0.0.1:{port}", UNIT):
        yield "127.0.0.1", port


@pytest.fixture
def loop() -> Iterator[asyncio.AbstractEventLoop]:
    """asyncio's default event loop, one per client."""
    loop = asyncio.new_event_loop()
    try:
        yield loop
    finally:
        loop.close()


def _rounds(benchmark: Any, one_round: Callable[[], tuple[float, float]], n: int = N) -> None:
    """``one_round() -> (cpu seconds, wall seconds)`` of ``n`` transactions, ROUNDS times."""
    cpu: list[float] = []
    tps: list[float] = []

    def run() -> None:
        c, w = one_round()
        cpu.append(c / n * 1e6)
        tps.append(n / w)

    benchmark.group = GROUP
    benchmark.pedantic(run, rounds=ROUNDS, iterations=1, warmup_rounds=0)
    benchmark.extra_info.update(transactions=n, cpu_us_per_tx=cpu, tps=tps)


def _timed(
    loop: asyncio.AbstractEventLoop,
    batch: Callable[[], Awaitable[Any]],
    size: int = 1,
    n: int = N,
) -> tuple[float, float]:
    """``n`` transactions as n / ``size`` awaits of ``batch()`` (``size`` reads each)."""

    async def all_of_them() -> None:
        for _ in range(n // size):
            await batch()

    c0, w0 = time.process_time(), time.perf_counter()
    loop.run_until_complete(all_of_them())
    return time.process_time() - c0, time.perf_counter() - w0


def test_libmodbus(benchmark: Any, binaries: PeerBinaries, server: tuple[str, int]) -> None:
    host, port = server

    def one_round() -> tuple[float, float]:
        r = libmodbus_bench(binaries, f"tcp:{host}:{port}", UNIT, N, warmup=WARMUP)
        assert r["errors"] == 0 and r["wrong"] == 0, r
        return float(r["cpu_seconds"]), float(r["seconds"])

    _rounds(benchmark, one_round)


@pytest.mark.parametrize(
    ("backend", "in_flight"),
    [("c", 1), ("python", 1), ("c", PIPELINE)],
    ids=["pyrtu async c", "pyrtu async twin", f"pyrtu async {PIPELINE} in flight"],
)
def test_pyrtu_async(
    benchmark: Any,
    server: tuple[str, int],
    loop: asyncio.AbstractEventLoop,
    backend: str,
    in_flight: int,
) -> None:
    import pyrtu

    if backend not in pyrtu.available_backends():
        pytest.skip(f"the {backend} backend is not available")
    host, port = server
    m = AsyncMaster(f"tcp://{host}:{port}", timeout=2.0, backend=backend, max_in_flight=in_flight)

    def batch() -> Awaitable[Any]:
        if in_flight == 1:
            return m.read_holding_registers(UNIT, ADDRESS, COUNT)
        return asyncio.gather(
            *(m.read_holding_registers(UNIT, ADDRESS, COUNT) for _ in range(in_flight))
        )

    async def warm() -> None:
        for _ in range(WARMUP):
            assert await m.read_holding_registers(UNIT, ADDRESS, COUNT) == EXPECTED

    n = N if in_flight == 1 else PIPELINED_N
    try:
        loop.run_until_complete(warm())
        _rounds(benchmark, lambda: _timed(loop, batch, in_flight, n), n)
        loop.run_until_complete(warm())
        assert m.counters["responses"] == 2 * WARMUP + ROUNDS * n
    finally:
        loop.run_until_complete(m.close())


def test_pymodbus_async(
    benchmark: Any, server: tuple[str, int], loop: asyncio.AbstractEventLoop
) -> None:
    from pymodbus.client import AsyncModbusTcpClient

    host, port = server

    async def made() -> AsyncModbusTcpClient:  # (its constructor wants a running loop)
        return AsyncModbusTcpClient(host, port=port, timeout=2.0)

    client = loop.run_until_complete(made())

    async def warm() -> None:
        assert await client.connect()
        for _ in range(WARMUP):
            r = await client.read_holding_registers(ADDRESS, count=COUNT, device_id=UNIT)
            assert r.registers == EXPECTED

    def batch() -> Awaitable[Any]:
        return client.read_holding_registers(ADDRESS, count=COUNT, device_id=UNIT)

    async def stop() -> None:
        client.close()

    try:
        loop.run_until_complete(warm())
        _rounds(benchmark, lambda: _timed(loop, batch))
    finally:
        loop.run_until_complete(stop())


def test_asyncio_floor(
    benchmark: Any, server: tuple[str, int], loop: asyncio.AbstractEventLoop
) -> None:
    host, port = server
    # [TCP] 3.1.3 / [AP] 6.3: the read and its answer, built here from the pattern
    pdu = struct.pack(">BHH", 3, ADDRESS, COUNT)
    tail = struct.pack(">HHB", 0, 1 + len(pdu), UNIT) + pdu
    answer_pdu = struct.pack(f">BB{COUNT}H", 3, 2 * COUNT, *EXPECTED)
    answer_tail = struct.pack(">HHB", 0, 1 + len(answer_pdu), UNIT) + answer_pdu
    size = 2 + len(answer_tail)

    class Floor(asyncio.Protocol):
        def __init__(self) -> None:
            self.got = b""
            self.done: asyncio.Future[bytes] | None = None

        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            assert isinstance(transport, asyncio.Transport)
            self.transport = transport

        def data_received(self, data: bytes) -> None:
            self.got += data
            if len(self.got) >= size and self.done is not None:
                self.done.set_result(self.got)
                self.got = b""

    async def connect() -> tuple[asyncio.Transport, Floor]:
        t, p = await loop.create_connection(Floor, host, port)
        return t, p

    transport, floor = loop.run_until_complete(connect())
    tid = 0

    async def read() -> None:
        nonlocal tid
        tid = (tid + 1) & 0xFFFF
        head = struct.pack(">H", tid)
        floor.done = loop.create_future()
        transport.write(head + tail)
        got = await floor.done
        assert got == head + answer_tail, got

    async def warm() -> None:
        for _ in range(WARMUP):
            await read()

    try:
        loop.run_until_complete(warm())
        _rounds(benchmark, lambda: _timed(loop, read))
    finally:
        transport.close()
        loop.run_until_complete(asyncio.sleep(0.05))  # (the server takes one client at a time)
