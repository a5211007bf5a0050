"""`TcpServer` answering Modbus over UDP (``start(..., udp=(host, port))``): pymodbus's
``ModbusUdpClient`` and ``AsyncModbusUdpClient`` as independent clients, raw datagram
sockets whose frames are built with `struct` ([TCP] 3.1.3), answers byte for byte as
on the TCP listener; datagrams that are not one Modbus ADU dropped and counted; the
access policy by client address and the audit trail as on TCP."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
from pathlib import Path
from typing import Any

import pytest
from waiting import wait_for

from pyrtu import DataStore
from pyrtu.gateway import Gateway, GatewayLimits
from pyrtu.security import AuditTrail, parse_policy
from pyrtu.tcp.server import LocalBus, TcpServer

TIMEOUT = 2.0

POLICY = """\
[[rule]]
name = "local"
clients = ["127.0.0.1"]
units = "1"
holding_registers = "0-9"

[[rule]]
name = "neighbour"
clients = ["127.0.0.2/32"]
read_only = true
"""


def store() -> DataStore:
    s = DataStore()
    s.holding_registers.add_range(0, list(range(100, 120)))
    s.input_registers.add_range(0, list(range(200, 220)))
    s.coils.add_range(0, [False] * 16)
    s.discrete_inputs.add_range(0, [i % 3 == 0 for i in range(16)])
    return s


class Server:
    """A `TcpServer` on the ``loop`` thread, listening on TCP and UDP."""

    def __init__(self, loop: asyncio.AbstractEventLoop, server: TcpServer) -> None:
        self.loop, self.server = loop, server
        start = server.start("127.0.0.1", 0, udp=("127.0.0.1", 0))
        asyncio.run_coroutine_threadsafe(start, loop).result(10)
        assert server.address is not None and server.udp_address is not None
        self.tcp_port, self.port = server.address[1], server.udp_address[1]

    def on_loop(self, call: Any) -> Any:
        async def get() -> Any:
            return call()

        return asyncio.run_coroutine_threadsafe(get(), self.loop).result(10)

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(10)


def adu(tid: int, unit: int, body: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(body) + 1, unit) + body


def over_udp(port: int, request: bytes, source: str = "127.0.0.1") -> bytes:
    """One request datagram from ``source``; the answer datagram."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((source, 0))
        s.settimeout(TIMEOUT)
        s.sendto(request, ("127.0.0.1", port))
        data, sender = s.recvfrom(65535)
        assert sender == ("127.0.0.1", port)
        return data


def over_tcp(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT) as s:
        s.sendall(request)
        data = b""
        while len(data) < 6 or len(data) < 6 + struct.unpack(">H", data[4:6])[0]:
            chunk = s.recv(512)
            assert chunk, "closed"
            data += chunk
        return data


def test_pymodbus_udp_clients_against_pyrtu(loop: asyncio.AbstractEventLoop) -> None:
    from pymodbus.client import AsyncModbusUdpClient, ModbusUdpClient

    data = store()
    server = Server(loop, TcpServer.for_store(1, data))
    client = ModbusUdpClient("127.0.0.1", port=server.port, timeout=TIMEOUT, retries=0)
    try:
        assert client.connect()
        assert client.read_holding_registers(0, count=5, device_id=1).registers == [
            100, 101, 102, 103, 104,
        ]  # fmt: skip
        assert client.read_input_registers(3, count=2, device_id=1).registers == [203, 204]
        bits = client.read_discrete_inputs(0, count=6, device_id=1).bits[:6]
        assert bits == [True, False, False, True, False, False]
        assert not client.write_registers(7, [7, 65535], device_id=1).isError()
        assert not client.write_coil(2, True, device_id=1).isError()
        rr = client.read_holding_registers(500, count=1, device_id=1)
        assert rr.isError() and rr.exception_code == 2
        assert data.holding_registers.get(8) == 65535 and data.coils.get(2) is True
    finally:
        client.close()

    async def main() -> None:
        aclient = AsyncModbusUdpClient("127.0.0.1", port=server.port, timeout=TIMEOUT, retries=0)
        await aclient.connect()
        try:
            rr = await aclient.read_holding_registers(7, count=2, device_id=1)
            assert rr.registers == [7, 65535]
            assert not (await aclient.write_register(0, 42, device_id=1)).isError()
        finally:
            aclient.close()

    try:
        asyncio.run(main())
        assert data.holding_registers.get(0) == 42
        counters = server.on_loop(lambda: server.server.counters)
        assert counters["requests"] == 8 and counters["bad_datagrams"] == 0
    finally:
        server.close()


def test_answers_byte_for_byte_as_over_tcp(loop: asyncio.AbstractEventLoop) -> None:
    server = Server(loop, TcpServer.for_store(1, store()))
    try:
        cases = [
            (1, struct.pack(">BHH", 3, 2, 3)),  # FC 03
            (1, struct.pack(">BHH", 4, 0, 1)),  # FC 04
            (255, struct.pack(">BHH", 1, 0, 16)),  # unit 0xFF: the device itself
            (0, struct.pack(">BHH", 2, 0, 9)),  # unit 0: the device itself too (4.4.1.2)
            (1, struct.pack(">BHH", 3, 900, 1)),  # no such address: exception 2
            (9, struct.pack(">BHH", 3, 0, 1)),  # another unit: exception 0x0A
            (1, bytes([0x41])),  # no such function: exception 1
        ]
        for tid, (unit, request) in enumerate(cases, 0x7FF0):
            answer = over_udp(server.port, adu(tid, unit, request))
            assert answer == over_tcp(server.tcp_port, adu(tid, unit, request)), request.hex()
            assert answer[:2] == struct.pack(">H", tid) and answer[6] == unit
        expected = adu(5, 1, struct.pack(">BBHHH", 3, 6, 102, 103, 104))
        assert over_udp(server.port, adu(5, 1, struct.pack(">BHH", 3, 2, 3))) == expected
    finally:
        server.close()


def test_datagrams_that_are_no_adu_are_dropped_and_counted(
    loop: asyncio.AbstractEventLoop,
) -> None:
    server = Server(loop, TcpServer.for_store(1, store()))
    read = struct.pack(">BHH", 3, 0, 1)
    good = adu(1, 1, read)
    bad = [
        b"",  # an empty datagram
        b"\x00\x01\x00",  # a part of a header
        good[:-1],  # cut short
        good + b"\x00",  # an ADU and a byte more
        good + good,  # two ADUs in one datagram
        adu(1, 1, read, protocol=1),  # not Modbus
        struct.pack(">HHHB", 1, 0, 300, 1) + bytes(299),  # length beyond 254
        b"\xff" * 1000,
    ]
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.settimeout(0.3)
            for datagram in bad:
                s.sendto(datagram, ("127.0.0.1", server.port))
            s.settimeout(TIMEOUT)
            s.sendto(good, ("127.0.0.1", server.port))  # the server goes on: answered
            assert s.recv(65535) == adu(1, 1, struct.pack(">BBH", 3, 2, 100))
            s.settimeout(0.2)
            with pytest.raises(TimeoutError):
                s.recv(65535)  # nothing answered the bad ones
        stats = server.on_loop(server.server.stats)
        assert stats["bad_datagrams"] == len(bad) and stats["requests"] == 1
        assert server.on_loop(server.server.health) == []
    finally:
        server.close()


def test_the_policy_knows_a_udp_client_by_its_address(
    loop: asyncio.AbstractEventLoop, tmp_path: Path
) -> None:
    data = store()
    trail = AuditTrail.open(tmp_path / "audit.jsonl")
    server = Server(
        loop,
        TcpServer.for_store(1, data, policy=parse_policy(POLICY, "p.toml"), audit=trail),
    )

    def refused(tid: int, unit: int, function: int) -> bytes:
        return struct.pack(">HHHBBB", tid, 0, 3, unit, function | 0x80, 1)

    try:
        write9 = struct.pack(">BHH", 6, 9, 0xBEEF)  # the last address the rule allows
        assert over_udp(server.port, adu(1, 1, write9)) == adu(1, 1, write9)
        write10 = struct.pack(">BHH", 6, 10, 0xBEEF)
        assert over_udp(server.port, adu(2, 1, write10)) == refused(2, 1, 6)
        read = struct.pack(">BHH", 3, 15, 2)
        answer = over_udp(server.port, adu(3, 1, read), source="127.0.0.2")
        assert answer == adu(3, 1, struct.pack(">BBHH", 3, 4, 115, 116))
        coil = struct.pack(">BHH", 5, 0, 0xFF00)
        assert over_udp(server.port, adu(4, 1, coil), source="127.0.0.2") == refused(4, 1, 5)
        assert data.holding_registers.get(9) == 0xBEEF
        assert data.holding_registers.get(10) == 110 and data.coils.get(0) is False
        stats = server.on_loop(server.server.stats)
        assert stats["denied"] == 2 and stats["denied_by"] == {"address": 1, "read_only": 1}
        assert stats["audited_writes"] == 1
    finally:
        server.close()
        trail.close()
    (record,) = [json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()]
    assert record["client"] == "127.0.0.1" and isinstance(record["port"], int)
    assert (record["function"], record["address"], record["values"]) == (6, 9, [0xBEEF])


def test_udp_clients_are_connections_of_the_table() -> None:
    """Each client address is one entry of the gateway's table: counted, forgotten
    after the idle timeout, and a full table makes a newcomer evict the idlest."""

    class App:
        addresses = frozenset({1})

        def execute(self, unit: int, request: bytes) -> bytes | None:
            return bytes([request[0], 2, 0, 7])

    async def ask(gateway: Gateway, sock: socket.socket, tid: int) -> None:
        loop = asyncio.get_running_loop()
        assert gateway.udp_address is not None
        await loop.sock_sendto(sock, adu(tid, 1, struct.pack(">BHH", 3, 0, 1)), gateway.udp_address)
        answer = await asyncio.wait_for(loop.sock_recv(sock, 512), TIMEOUT)
        assert answer == adu(tid, 1, bytes([3, 2, 0, 7]))

    async def main() -> None:
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
        for s in socks:
            s.setblocking(False)
        # a full table: the third client evicts the idlest
        limits = GatewayLimits(max_connections=2, idle_timeout=0)
        gateway = Gateway([(LocalBus(App()), {1: 1})], limits)
        await gateway.start("127.0.0.1", None, udp=("127.0.0.1", 0))
        assert gateway.address is None and gateway.udp_address is not None
        try:
            for tid, s in enumerate(socks):
                await ask(gateway, s, tid)
            stats = gateway.stats()
            assert stats["connections"] == 3 and stats["evicted"] == 1
            assert stats["open_connections"] == 2
            await ask(gateway, socks[0], 9)  # the evicted one: a newcomer again
            assert gateway.stats()["connections"] == 4
        finally:
            await gateway.close()
        assert gateway.health() == ["the gateway is not running"]
        # the idle timeout forgets a client
        gateway = Gateway([(LocalBus(App()), {1: 1})], GatewayLimits(idle_timeout=0.2))
        await gateway.start("127.0.0.1", None, udp=("127.0.0.1", 0))
        try:
            await ask(gateway, socks[0], 1)
            await wait_for(lambda: gateway.stats()["open_connections"] == 0, "idle peer", 20)
            assert gateway.counters["idle_timeouts"] == 1
            await ask(gateway, socks[0], 2)  # then served as a new one
            assert gateway.counters["connections"] == 2
        finally:
            await gateway.close()
            for s in socks:
                s.close()

    asyncio.run(main())


def test_udp_newcomers_evict_udp_peers_before_tcp_connections() -> None:
    """A full table of an idle TCP connection and an idle UDP peer: a datagram from a
    new address takes the UDP peer's place, the TCP client stays connected."""

    class App:
        addresses = frozenset({1})

        def execute(self, unit: int, request: bytes) -> bytes | None:
            return bytes([request[0], 2, 0, 9])

    async def main() -> None:
        loop = asyncio.get_running_loop()
        gateway = Gateway([(LocalBus(App()), {1: 1})], GatewayLimits(max_connections=2))
        await gateway.start("127.0.0.1", 0, udp=("127.0.0.1", 0))
        assert gateway.address is not None and gateway.udp_address is not None
        request = struct.pack(">BHH", 3, 0, 1)
        reader, writer = await asyncio.open_connection(*gateway.address)
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
        try:
            writer.write(adu(1, 1, request))
            assert await asyncio.wait_for(reader.readexactly(11), TIMEOUT) == adu(
                1, 1, bytes([3, 2, 0, 9])
            )
            for tid, s in enumerate(socks, 2):  # the first peer idle, then a newcomer
                s.setblocking(False)
                await loop.sock_sendto(s, adu(tid, 1, request), gateway.udp_address)
                answer = await asyncio.wait_for(loop.sock_recv(s, 512), TIMEOUT)
                assert answer == adu(tid, 1, bytes([3, 2, 0, 9]))
            assert gateway.counters["evicted"] == 1
            writer.write(adu(9, 1, request))  # the TCP client was not evicted
            assert await asyncio.wait_for(reader.readexactly(11), TIMEOUT) == adu(
                9, 1, bytes([3, 2, 0, 9])
            )
            assert gateway.stats()["open_connections"] == 2
        finally:
            writer.close()
            for s in socks:
                s.close()
            await gateway.close()

    asyncio.run(main())


def test_bad_listen_arguments_name_themselves() -> None:
    async def main() -> None:
        server = TcpServer.for_store(1, store())
        with pytest.raises(TypeError, match=r"^udp must be a \(host, port\) pair"):
            await server.start("127.0.0.1", 0, udp="127.0.0.1:5020")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match=r"^udp: port must be 0\.\.65535"):
            await server.start("127.0.0.1", 0, udp=("127.0.0.1", 70000))
        with pytest.raises(ValueError, match="port: None"):
            await server.start("127.0.0.1", None)
        assert server.address is None and server.udp_address is None
        taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        taken.bind(("127.0.0.1", 0))
        try:
            with pytest.raises(OSError):
                await server.start("127.0.0.1", 0, udp=taken.getsockname())
            assert server.udp_address is None
            assert server.health() == ["the gateway is not running"]
        finally:
            taken.close()
        await server.start("127.0.0.1", 0, udp=("127.0.0.1", 0))  # what failed left nothing
        await server.close()

    asyncio.run(main())


def test_serve_forever_over_udp_only() -> None:
    async def main() -> None:
        server = TcpServer.for_store(1, store())
        task = asyncio.create_task(server.serve_forever("127.0.0.1", None, udp=("127.0.0.1", 0)))
        await wait_for(lambda: server.udp_address is not None, "the UDP listener", 20)
        assert server.address is None and server.udp_address is not None
        loop = asyncio.get_running_loop()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setblocking(False)
            await loop.sock_sendto(s, adu(3, 1, struct.pack(">BHH", 4, 1, 2)), server.udp_address)
            answer = await asyncio.wait_for(loop.sock_recv(s, 512), TIMEOUT)
        assert answer == adu(3, 1, struct.pack(">BBHH", 4, 4, 201, 202))
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert server.health() == ["the gateway is not running"]

    asyncio.run(main())
