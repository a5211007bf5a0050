"""``Master("tcp://...")`` and ``AsyncMaster("tcp://...")`` (Modbus TCP), and the
``rtu+tcp://`` masters, against real servers on 127.0.0.1: pymodbus's and libmodbus's
TCP servers, and socat joining TCP to a pty with a pyrtu slave (RTU over TCP)."""

from __future__ import annotations

import asyncio
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from peers import pattern
from peers.tools import (
    PeerBinaries,
    free_tcp_port,
    libmodbus_server,
    pymodbus_server,
    pyrtu_slave_process,
)

from pyrtu import ExceptionResponseError, Master, NoResponseError, PortError
from pyrtu.aio import AsyncMaster

pytest_plugins = ["peers.fixtures"]

WINDOW = {"pymodbus": 1, "libmodbus": 8}  # see test_tcp_client.py


@pytest.fixture(params=["pymodbus", "libmodbus"])
def tcp_server(
    request: pytest.FixtureRequest, peer_binaries: PeerBinaries
) -> Iterator[tuple[str, int]]:
    port = free_tcp_port()
    if request.param == "pymodbus":
        peer = pymodbus_server(f"127.0.0.1:{port}", 1, mode="tcp")
    else:
        peer = libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1)
    with peer:
        yield f"tcp://127.0.0.1:{port}", WINDOW[request.param]


def test_master_over_modbus_tcp(tcp_server: tuple[str, int]) -> None:
    url, _ = tcp_server
    with Master(url, timeout=2.0) as m:
        assert type(m).__name__ == "TcpMaster" and isinstance(m, Master)
        assert m.read_holding_registers(1, 0, 10) == pattern.holdings(1, 0, 10)
        assert m.read_input_registers(1, 3, 4) == pattern.inputs(1, 3, 4)
        assert m.read_coils(1, 0, 30) == pattern.coils(1, 0, 30)
        assert m.read_discrete_inputs(1, 7, 9) == pattern.discretes(1, 7, 9)
        m.write_register(1, 10, 555)
        m.write_registers(1, 20, [1, 2, 3])
        m.write_coil(1, 4, True)
        m.write_coils(1, 40, [True, False, True])
        assert m.read_holding_registers(1, 10, 1) == [555]
        assert m.read_holding_registers(1, 20, 3) == [1, 2, 3]
        assert m.read_coils(1, 40, 3) == [True, False, True]
        assert m.read_write_registers(1, 20, 2, 30, [9, 8]) == [1, 2]
        with pytest.raises(ExceptionResponseError) as info:
            m.read_holding_registers(1, 60000, 5)
        assert info.value.code == 2
        with pytest.raises(ValueError, match="count"):
            m.read_holding_registers(1, 0, 0)  # checked before anything is sent
        assert m.counters["responses"] == 12 and m.counters["exceptions"] == 1
        assert "Modbus TCP" in repr(m)


def test_async_master_over_modbus_tcp(tcp_server: tuple[str, int]) -> None:
    url, window = tcp_server

    async def main() -> None:
        async with AsyncMaster(url, timeout=2.0, max_in_flight=window) as m:
            reads = [m.read_holding_registers(1, i, 3) for i in range(30)]
            assert await asyncio.gather(*reads) == [pattern.holdings(1, i, 3) for i in range(30)]
            await m.write_register(1, 11, 1234)
            assert await m.read_holding_registers(1, 11, 1) == [1234]
            with pytest.raises(ExceptionResponseError):
                await m.read_input_registers(1, 60000, 1)

    asyncio.run(main())


def test_bad_urls_and_dead_servers() -> None:
    with pytest.raises(ValueError, match="tcp://"):
        Master("tcp://host:notaport")
    with pytest.raises(PortError, match="cannot connect"):
        Master(f"tcp://127.0.0.1:{free_tcp_port()}", timeout=1.0)
    with pytest.raises(ValueError, match="timeout"):
        Master("tcp://127.0.0.1:1", timeout=0)

    async def main() -> None:
        m = AsyncMaster(f"tcp://127.0.0.1:{free_tcp_port()}", timeout=1.0)
        with pytest.raises(PortError, match="cannot connect"):
            await m.read_coils(1, 0, 1)

    asyncio.run(main())


def test_retries_and_timeout_on_a_silent_server() -> None:
    import socket

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    url = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    try:
        with Master(url, timeout=0.1, retries=2) as m:
            with pytest.raises(NoResponseError):
                m.read_holding_registers(1, 0, 1)
            assert m.counters["timeouts"] == 3 and m.counters["requests"] == 3
            m.timeout = 0.05
            assert m.timeout == 0.05
    finally:
        listener.close()


@pytest.fixture
def rtu_device_server(tmp_path: Path) -> Iterator[str]:
    """A pyrtu slave (address 4) behind socat: rtu+tcp:// URL."""
    port = free_tcp_port()
    link = tmp_path / "serial"
    proc = subprocess.Popen(
        ["socat", f"PTY,link={link},raw,echo=0", f"TCP-LISTEN:{port},bind=127.0.0.1,reuseaddr"],
        stderr=subprocess.DEVNULL,
    )
    for _ in range(200):
        if link.exists():
            break
        time.sleep(0.01)
    try:
        with pyrtu_slave_process(str(link), 4, t35=0):
            yield f"rtu+tcp://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(5)


def test_masters_over_rtu_tcp(rtu_device_server: str) -> None:
    with Master(rtu_device_server, timeout=1.0) as m:
        assert type(m).__name__ == "RtuTcpMaster" and m.t35 == 0
        assert m.read_holding_registers(4, 5, 5) == pattern.holdings(4, 5, 5)
        m.write_register(4, 8, 99)
        assert m.read_holding_registers(4, 8, 1) == [99]
        assert m.counters["crc_errors"] == 0


def test_async_master_over_rtu_tcp(rtu_device_server: str) -> None:
    async def main() -> None:
        async with AsyncMaster(rtu_device_server, timeout=1.0) as m:
            got = await asyncio.gather(*(m.read_input_registers(4, i, 2) for i in range(10)))
            assert got == [pattern.inputs(4, i, 2) for i in range(10)]

    asyncio.run(main())


def _serial_attributes(m: Master | AsyncMaster, url: str) -> None:
    """What a TCP master answers in place of a serial line's properties."""
    with pytest.raises(AttributeError, match="no serial line") as info:
        _ = m.line
    assert url in str(info.value)
    assert not hasattr(m, "line") and getattr(m, "line", None) is None
    assert not hasattr(m, "port")
    assert (m.mode, m.t35, m.echo, m.broadcast_delay) == ("tcp", 0.0, False, 0.0)
    assert m.url == url  # type: ignore[union-attr]


def test_tcp_master_in_place_of_a_serial_one(tcp_server: tuple[str, int]) -> None:
    """`Master`'s serial-line properties on a TCP master: a value where TCP has one, a
    clear AttributeError for the line itself; last_answer_time stamps each answer."""
    url, _ = tcp_server
    with Master(url, timeout=2.0) as m:
        _serial_attributes(m, url)
        assert m.last_answer_time is None
        before = time.monotonic()
        assert m.read_holding_registers(1, 0, 2) == pattern.holdings(1, 0, 2)
        first = m.last_answer_time
        assert first is not None and before <= first <= time.monotonic()
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(1, 60000, 1)
        assert m.last_answer_time is not None and m.last_answer_time >= first  # an answer too

    async def main() -> None:
        async with AsyncMaster(url, timeout=2.0) as am:
            _serial_attributes(am, url)
            assert am.last_answer_time is None  # not even connected yet
            before = time.monotonic()
            assert await am.read_input_registers(1, 3, 2) == pattern.inputs(1, 3, 2)
            stamp = am.last_answer_time
            assert stamp is not None and before <= stamp <= time.monotonic()

    asyncio.run(main())


def test_poller_over_modbus_tcp() -> None:
    """A `pyrtu.Poller` bus on tcp:// (the AsyncMaster the poller opens is the TCP one,
    whose last_answer_time stamps the values), against pyrtu's TCP server."""
    import pyrtu
    from pyrtu.poller import Bus, Point
    from pyrtu.tcp_server import TcpServer

    async def main() -> None:
        store = pyrtu.DataStore()
        store.holding_registers.add_range(0, [100 + i for i in range(20)])
        async with await TcpServer.for_store(3, store).start("127.0.0.1", 0) as server:
            assert server.address is not None
            host, port = server.address
            bus = Bus("plant", f"tcp://{host}:{port}", {"timeout": 1.0})
            points = [
                Point("a", "plant", 3, "holding", 2, interval=0.02),
                Point("b", "plant", 3, "holding", 7, interval=0.02),
            ]
            got: dict[str, object] = {}

            async def watch(poller: pyrtu.Poller) -> None:
                async for update in poller.updates():
                    got[update.name] = update.value
                    if len(got) == 2:
                        break
                assert got == {"a": 102, "b": 107}
                store.holding_registers.set(7, 555)  # a later poll sees it
                async for update in poller.updates():
                    if update.name == "b" and update.value == 555:
                        break

            async with pyrtu.Poller(buses=[bus], points=points) as poller:
                # (a bound on a hang, not a timing: the updates come every 20 ms)
                await asyncio.wait_for(watch(poller), 30.0)

    asyncio.run(main())
