"""`pyrtu.tcp.server.TcpServer`: a slave's DataStore and handlers over Modbus TCP, to
pymodbus's and libmodbus's TCP clients and pyrtu's; a Slave and an AsyncSlave that
serve their serial port and TCP at once (one DataStore).  127.0.0.1 only."""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest
from mbap_wire import read_adu
from peers import pattern
from peers.tools import PeerBinaries, libmodbus_script

from pyrtu import ExceptionResponseError, Master, Slave, pdu
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.aio_slave import AsyncSlave
from pyrtu.tcp import AsyncTcpClient, TcpClient
from pyrtu.tcp.server import TcpServer

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
        client.write_register(60, 61, device_id=0, no_response_expected=True)  # unit 0
    finally:
        client.close()
    with Master(url, timeout=2.0) as m:  # unit 0, the device itself, executed it
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


def test_unit_0_and_0xff_are_the_device_itself_and_answered(
    running, peer_binaries: PeerBinaries
) -> None:  # type: ignore[no-untyped-def]
    """Messaging on TCP/IP Implementation Guide 4.4.1.2: 0xFF addresses a TCP device
    directly, "the value 0 is also accepted": libmodbus's client (its unit-test-client
    asserts "Reply after a query with unit id == 0") gets answers for both, under
    their own unit id; another unit id is still 0x0A."""
    import struct

    from pyrtu import encode_mbap, parse_tcp_stream

    url = serve(running, TcpServer.for_store(7, pattern.pattern_store(7)))
    device = "tcp:" + url[6:]
    r = libmodbus_script(
        peer_binaries, device, 0, ["r03:0:3", "slave:8", "r03:0:1"], timeout_ms=2000
    )
    assert r[0]["values"] == pattern.holdings(7, 0, 3)  # unit 0: answered, not a broadcast
    assert r[2]["exception"] == 0x0A
    host, port = url[6:].split(":")
    with socket.create_connection((host, int(port)), timeout=5) as s:
        for tid, unit in ((0x1234, 0), (0x1235, 0xFF)):
            s.sendall(encode_mbap(tid, unit, pdu.write_register_request(9, tid)))
            head = s.recv(6, socket.MSG_WAITALL)
            body = s.recv(struct.unpack(">H", head[4:])[0], socket.MSG_WAITALL)
            (answer,) = parse_tcp_stream(head + body, "master")
            assert (answer.transaction, answer.unit) == (tid, unit)  # under its own unit id
            assert answer.pdu == pdu.write_register_request(9, tid)


def test_start_twice_raises_and_leaks_no_listener() -> None:
    async def main() -> None:
        server = TcpServer.for_store(1, pattern.pattern_store(1))
        await server.start("127.0.0.1", 0)
        first = server.address
        assert first is not None
        with pytest.raises(RuntimeError, match="already listens"):
            await server.start("127.0.0.1", 0)
        assert server.address == first
        await server.close()
        with pytest.raises(ConnectionRefusedError):  # nothing listens any more
            await asyncio.open_connection(*first)
        await server.start("127.0.0.1", 0)  # closed, it may start again
        async with await AsyncTcpClient.connect(
            f"tcp://127.0.0.1:{server.address[1]}",
            timeout=2.0,  # type: ignore[index]
        ) as c:
            assert pdu.parse_registers(await c.request(1, pdu.read_request(3, 0, 1)) or b"", 1) == (
                pattern.holdings(1, 0, 1)
            )
        await server.close()

    asyncio.run(main())


def test_arguments_are_checked_naming_them() -> None:
    from pyrtu import DataStore

    for address, error in (("x", TypeError), (1.5, TypeError), ([True], TypeError),
                           (300, ValueError), ([], ValueError)):  # fmt: skip
        with pytest.raises(error, match="address"):
            TcpServer.for_store(address)  # type: ignore[arg-type]
    for store in (42, "store", [DataStore()], {1: 42}):
        with pytest.raises(TypeError, match="store"):
            TcpServer.for_store(1, store)  # type: ignore[arg-type]
    server = TcpServer.for_store(1, DataStore())

    async def main() -> None:
        for port, error in ((99999, ValueError), (-1, ValueError), ("502", TypeError),
                            (True, TypeError)):  # fmt: skip
            with pytest.raises(error, match="port"):
                await server.start("127.0.0.1", port)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="host"):
            await server.start(5, 0)  # type: ignore[arg-type]
        assert server.address is None  # nothing was bound

    asyncio.run(main())


def _adu(transaction: int, protocol: int, unit: int, body: bytes) -> bytes:
    """An MBAP ADU built here with `struct` (length = unit id + PDU, [TCP] 3.1.3)."""
    return struct.pack(">HHHB", transaction, protocol, len(body) + 1, unit) + body


def test_requests_read_whole_or_in_pieces_are_answered_alike(running) -> None:  # type: ignore[no-untyped-def]
    """A read holding one whole request is told by its header alone, at the limits
    of [AP] 4.1 / [TCP] 3.1.3 (a length of 2 and of 254); pieces, several requests in
    one read and a bad header go through the framer: the same answers either way."""
    server = TcpServer.for_store(1, pattern.pattern_store(1))
    url = serve(running, server)
    host, port = url[6:].split(":")
    read = bytes((3, 0, 4, 0, 2))  # holding registers 4..5
    regs = pattern.holdings(1, 4, 2)
    answer = struct.pack(">BBHH", 3, 4, *regs)
    illegal = bytes((0xC1, 1))  # function 0x41: exception 01, illegal function
    with socket.create_connection((host, int(port)), timeout=5) as s:
        s.sendall(_adu(0x1234, 0, 1, read))
        assert read_adu(s) == _adu(0x1234, 0, 1, answer)
        s.sendall(_adu(7, 0, 1, b"\x41"))  # length 2: the shortest
        assert read_adu(s) == _adu(7, 0, 1, illegal)
        s.sendall(_adu(8, 0, 0xFF, b"\x41" + bytes(252)))  # length 254: the longest
        assert read_adu(s) == _adu(8, 0, 0xFF, illegal)
        whole = _adu(9, 0, 1, read)
        s.sendall(whole[:5])  # a header in two pieces
        time.sleep(0.05)
        s.sendall(whole[5:])
        assert read_adu(s) == _adu(9, 0, 1, answer)
        s.sendall(_adu(10, 0, 1, read) + _adu(11, 0, 1, read))  # two in one write
        assert read_adu(s) == _adu(10, 0, 1, answer)
        assert read_adu(s) == _adu(11, 0, 1, answer)
    counters = server.counters
    assert counters["requests"] == 6 and counters["answers"] == 4
    assert counters["exceptions"] == 2 and counters["bad_headers"] == 0
    for bad in (
        _adu(12, 0, 1, b"\x41" + bytes(253)),  # length 255: one over
        _adu(13, 1, 1, read),  # protocol id 1
        struct.pack(">HHHB", 14, 0, 1, 1),  # length 1: no function code
    ):
        with socket.create_connection((host, int(port)), timeout=5) as s:
            s.sendall(bad)
            assert s.recv(100) == b""  # closed, nothing answered
    assert server.counters["bad_headers"] == 3 and server.counters["requests"] == 6
