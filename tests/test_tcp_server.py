"""`pyrtu.tcp_server.TcpServer`: a slave's DataStore and handlers over Modbus TCP, to
pymodbus's and libmodbus's TCP clients and pyrtu's; a Slave and an AsyncSlave that
serve their serial port and TCP at once (one DataStore).  127.0.0.1 only."""

from __future__ import annotations

import asyncio
import socket
import threading
from collections.abc import Iterator

import pytest
from peers import pattern
from peers.tools import PeerBinaries, libmodbus_script

from pyrtu import ExceptionResponseError, Master, Slave, pdu
from pyrtu._aio_slave import AsyncSlave
from pyrtu.aio import AsyncMaster
from pyrtu.tcp import AsyncTcpClient, TcpClient
from pyrtu.tcp_server import TcpServer

pytest_plugins = ["peers.fixtures"]


@pytest.fixture
def running() -> Iterator[tuple[asyncio.AbstractEventLoop, list[TcpServer]]]:
    """An event loop in a thread, for servers the (blocking) clients talk to."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    servers: list[TcpServer] = []
    yield loop, servers
    for s in servers:
        asyncio.run_coroutine_threadsafe(s.close(), loop).result(10)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


def serve(running: tuple[asyncio.AbstractEventLoop, list[TcpServer]], server: TcpServer) -> str:
    loop, servers = running
    asyncio.run_coroutine_threadsafe(server.start("127.0.0.1", 0), loop).result(10)
    servers.append(server)
    assert server.address is not None
    return f"tcp://127.0.0.1:{server.address[1]}"


def test_pymodbus_client_against_the_server(running) -> None:  # type: ignore[no-untyped-def]
    from pymodbus.client import ModbusTcpClient

    url = serve(running, TcpServer.for_store(3, pattern.pattern_store(3)))
    host, port = url[6:].split(":")
    client = ModbusTcpClient(host, port=int(port), timeout=2, retries=0)
    assert client.connect()
    try:
        rr = client.read_holding_registers(5, count=10, device_id=3)
        assert rr.registers == pattern.holdings(3, 5, 10)
        rr = client.read_holding_registers(5, count=2, device_id=255)  # the server itself
        assert rr.registers == pattern.holdings(3, 5, 2)
        rr = client.read_coils(0, count=16, device_id=3)
        assert rr.bits[:16] == pattern.coils(3, 0, 16)
        assert not client.write_registers(50, [7, 8], device_id=3).isError()
        assert client.read_holding_registers(50, count=2, device_id=3).registers == [7, 8]
        rr = client.read_input_registers(60000, count=1, device_id=3)
        assert rr.isError() and rr.exception_code == 2
        rr = client.read_input_registers(0, count=1, device_id=4)
        assert rr.isError() and rr.exception_code == 0x0A  # not this server's unit
        client.write_register(60, 61, device_id=0, no_response_expected=True)  # broadcast
    finally:
        client.close()
    with Master(url, timeout=2.0) as m:  # the broadcast was executed, not answered
        assert m.read_holding_registers(3, 60, 1) == [61]


def test_libmodbus_client_against_the_server(running, peer_binaries: PeerBinaries) -> None:  # type: ignore[no-untyped-def]
    url = serve(running, TcpServer.for_store(1, pattern.pattern_store(1)))
    device = "tcp:" + url[6:]
    ops = ["r03:0:10", "r02:3:11", "w05:9:1", "r01:9:1", "m22:4:0x00ff:0x1200", "r03:4:1",
           "rw23:0:2:100:5,6", "r03:100:2", "r04:60000:1"]  # fmt: skip
    r = libmodbus_script(peer_binaries, device, 1, ops, timeout_ms=2000)
    assert r[0]["values"] == pattern.holdings(1, 0, 10)
    assert r[1]["values"] == [int(b) for b in pattern.discretes(1, 3, 11)]
    assert r[3]["values"] == [1]
    assert r[5]["values"] == [(pattern.holding(1, 4) & 0x00FF) | (0x1200 & ~0x00FF)]
    assert r[6]["values"] == pattern.holdings(1, 0, 2) and r[7]["values"] == [5, 6]
    assert r[8]["exception"] == 2


def test_many_connections_and_a_bad_one(running) -> None:  # type: ignore[no-untyped-def]
    url = serve(running, TcpServer.for_store(1, pattern.pattern_store(1)))
    host, port = url[6:].split(":")

    async def main() -> None:
        bad = socket.create_connection((host, int(port)))
        bad.sendall(bytes.fromhex("0001 0000 0100 01 03"))  # length 256
        clients = [await AsyncTcpClient.connect(url, timeout=5.0) for _ in range(20)]
        answers = await asyncio.gather(
            *(c.request(1, pdu.read_request(3, i, 2)) for i, c in enumerate(clients))
        )
        for i, a in enumerate(answers):
            assert a is not None and pdu.parse_registers(a, 2) == pattern.holdings(1, i, 2)
        bad.settimeout(5)
        assert bad.recv(100) == b""  # that connection was closed, nothing else
        bad.close()
        for c in clients:
            await c.close()

    asyncio.run(main())


def test_serial_and_tcp_share_one_slave(pty_pair: tuple[str, str], running) -> None:  # type: ignore[no-untyped-def]
    master_side, slave_side = pty_pair
    slave = Slave(slave_side, 2, pattern.pattern_store(2), baudrate=115200, parity="N", t35=0)
    slave.start()
    try:
        url = serve(running, TcpServer(slave))
        with Master(master_side, baudrate=115200, parity="N", t35=0, timeout=1.0) as serial_m:
            with TcpClient(url, timeout=2.0) as tcp:
                serial_m.write_register(2, 10, 1010)
                got = tcp.request(2, pdu.read_request(3, 10, 1))
                assert got is not None and pdu.parse_registers(got, 1) == [1010]
                tcp.request(2, pdu.write_register_request(11, 1111))
                assert serial_m.read_holding_registers(2, 11, 1) == [1111]
                with pytest.raises(ExceptionResponseError):
                    tcp.request(2, pdu.read_request(3, 60000, 1))
        assert slave.counters["requests"] >= 2
    finally:
        slave.close()


def test_async_slave_on_serial_and_tcp(pty_pair: tuple[str, str]) -> None:
    master_side, slave_side = pty_pair

    async def main() -> None:
        slave = AsyncSlave(slave_side, 5, pattern.pattern_store(5), baudrate=115200, parity="N",
                           t35=0)  # fmt: skip
        task = slave.start()
        server = await TcpServer(slave).start("127.0.0.1", 0)
        assert server.address is not None
        url = f"tcp://127.0.0.1:{server.address[1]}"
        try:
            async with AsyncMaster(master_side, baudrate=115200, parity="N", t35=0) as m:
                tcp = await AsyncTcpClient.connect(url, timeout=2.0)
                await m.write_register(5, 3, 303)
                got = await tcp.request(5, pdu.read_request(3, 3, 1))
                assert got is not None and pdu.parse_registers(got, 1) == [303]
                serial_reads = [m.read_input_registers(5, i, 1) for i in range(10)]
                tcp_reads = [tcp.request(5, pdu.read_request(4, i, 1)) for i in range(10)]
                results = await asyncio.gather(*serial_reads, *tcp_reads)
                assert results[:10] == [pattern.inputs(5, i, 1) for i in range(10)]
                assert [pdu.parse_registers(r, 1) for r in results[10:]] == results[:10]
                await tcp.close()
        finally:
            await server.close()
            await slave.stop()
            await task

    asyncio.run(main())


def test_rejects_an_object_that_is_no_slave() -> None:
    with pytest.raises(TypeError, match="execute"):
        TcpServer(object())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="address"):
        TcpServer.for_store(300)
