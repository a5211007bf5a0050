"""``Master("udp://...")`` and ``AsyncMaster("udp://...")``: Modbus over UDP (one MBAP
ADU per datagram), on both backends, against pymodbus's ``ModbusUdpServer`` (an
independent peer serving `peers.pattern`), pyrtu's own UDP listener, and datagram
servers scripted here on real loopback sockets (their frames built with `struct`
from [TCP] 3.1.3: transaction id, protocol id 0, length, unit id, PDU)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import threading
from collections.abc import Callable, Iterator
from types import ModuleType

import pytest
from peers import pattern
from peers.tools import free_tcp_port, pymodbus_server

from pyrtu import DataStore, ExceptionResponseError, Master, NoResponseError, PortError, pdu
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.tcp.server import TcpServer

TIMEOUT = 2.0  # only bounds how long a failure takes


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 nothing is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def adu(tid: int, unit: int, body: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(body) + 1, unit) + body


def registers(values: list[int]) -> bytes:
    """The response PDU of FC 03 ([AP] 6.3)."""
    return struct.pack(f">BB{len(values)}H", 3, 2 * len(values), *values)


@pytest.fixture(scope="module")
def pymodbus_udp() -> Iterator[int]:
    """pymodbus's UDP server (slave 1, and unit 255) on a free port: its port."""
    port = free_udp_port()
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="udp"):
        yield port


@pytest.fixture(scope="module")
def pymodbus_tcp() -> Iterator[int]:
    port = free_tcp_port()
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="tcp"):
        yield port


class Scripted:
    """A datagram server on 127.0.0.1: ``answer(request, client, sock)`` is called
    for each request datagram (in a thread) and sends what it likes."""

    def __init__(self, answer: Callable[[bytes, tuple[str, int], socket.socket], None]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = int(self.sock.getsockname()[1])
        self.url = f"udp://127.0.0.1:{self.port}"
        self.answer = answer
        self.requests: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, client = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            self.requests.append(data)
            self.answer(data, client, self.sock)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


@contextlib.contextmanager
def scripted(
    answer: Callable[[bytes, tuple[str, int], socket.socket], None],
) -> Iterator[Scripted]:
    server = Scripted(answer)
    try:
        yield server
    finally:
        server.close()


class Relay:
    """A UDP relay between a client and a server that drops the first ``drop``
    datagrams the client sends (datagram loss, as UDP has it)."""

    def __init__(self, server_port: int, drop: int = 1) -> None:
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(("127.0.0.1", server_port))
        self.url = f"udp://127.0.0.1:{self.front.getsockname()[1]}"
        self.drop = drop
        self.dropped = 0
        self.forwarded = 0
        self.client: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.1)
            for sock in ready:
                if sock is self.front:
                    data, self.client = self.front.recvfrom(65535)
                    if self.dropped < self.drop:
                        self.dropped += 1
                        continue
                    self.forwarded += 1
                    self.back.send(data)
                else:
                    data = self.back.recv(65535)
                    if self.client is not None:
                        self.front.sendto(data, self.client)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.front.close()
        self.back.close()


# -- against a real peer ---------------------------------------------------------------


def test_master_over_udp_against_pymodbus(pymodbus_udp: int, backend: ModuleType) -> None:
    url = f"udp://127.0.0.1:{pymodbus_udp}"
    with Master(url, timeout=TIMEOUT, backend=backend.BACKEND) as m:
        assert type(m) is Master and m.mode == "udp" and m.url == url
        assert "Modbus over UDP" in repr(m)
        assert m.read_holding_registers(1, 0, 10) == pattern.holdings(1, 0, 10)
        assert m.read_input_registers(1, 3, 4) == pattern.inputs(1, 3, 4)
        assert m.read_coils(1, 0, 30) == pattern.coils(1, 0, 30)
        assert m.read_discrete_inputs(1, 7, 9) == pattern.discretes(1, 7, 9)
        assert m.read_holding_registers(255, 0, 3) == pattern.holdings(1, 0, 3)  # a TCP unit id
        m.write_register(1, 500, 555)
        m.write_registers(1, 520, [1, 2, 3])
        assert m.read_holding_registers(1, 500, 1) == [555]
        assert m.read_holding_registers(1, 520, 3) == [1, 2, 3]
        with pytest.raises(ExceptionResponseError) as info:
            m.read_holding_registers(1, 60000, 5)
        assert info.value.code == 2
        with pytest.raises(ValueError, match="count"):
            m.read_holding_registers(1, 0, 0)  # checked before anything is sent
        assert m.counters["responses"] == 9 and m.counters["exceptions"] == 1
        assert m.counters["requests"] == 10 and m.counters["late"] == 0
        with pytest.raises(AttributeError, match="Modbus over UDP master has no serial line"):
            _ = m.line


def test_answers_byte_for_byte_as_over_tcp(pymodbus_udp: int, pymodbus_tcp: int) -> None:
    """The same request PDUs to pymodbus over UDP and over TCP: the same answers."""
    requests = [
        pdu.read_request(3, 0, 20),
        pdu.read_request(4, 100, 7),
        pdu.read_request(1, 3, 19),
        pdu.read_request(2, 0, 8),
        bytes([3, 0xEA, 0x60, 0, 1]),  # address 60000: exception 2
        pdu.device_id_request(1, 0),
    ]
    with (
        Master(f"udp://127.0.0.1:{pymodbus_udp}", timeout=TIMEOUT) as udp,
        Master(f"tcp://127.0.0.1:{pymodbus_tcp}", timeout=TIMEOUT) as tcp,
    ):
        for request in requests:
            assert udp.exchange(1, request) == tcp.exchange(1, request), request.hex()
    assert registers(pattern.holdings(1, 0, 3)) == udp_answer(
        pymodbus_udp, pdu.read_request(3, 0, 3)
    )


def udp_answer(port: int, request: bytes) -> bytes:
    with Master(f"udp://127.0.0.1:{port}", timeout=TIMEOUT) as m:
        return m.exchange(1, request)


def test_async_master_over_udp(pymodbus_udp: int, backend: ModuleType) -> None:
    async def main() -> None:
        url = f"udp://127.0.0.1:{pymodbus_udp}"
        async with AsyncMaster(url, timeout=TIMEOUT, backend=backend.BACKEND) as m:
            await m.connect()
            reads = [m.read_input_registers(1, i, 3) for i in range(20)]
            assert await asyncio.gather(*reads) == [pattern.inputs(1, i, 3) for i in range(20)]
            await m.write_register(1, 611, 1234)
            assert await m.read_holding_registers(1, 611, 1) == [1234]
            with pytest.raises(ExceptionResponseError):
                await m.read_input_registers(1, 60000, 1)
            assert m.counters["responses"] == 22 and m.mode == "udp"

    asyncio.run(main())


def test_async_master_pipelines_over_udp(backend: ModuleType) -> None:
    """Up to ``max_in_flight`` requests on the wire, answers matched by transaction id
    (pyrtu's UDP listener answers each datagram as it comes)."""

    async def main() -> None:
        store = DataStore()
        store.holding_registers.add_range(0, [(7 * i + 3) & 0xFFFF for i in range(100)])
        async with await TcpServer.for_store(1, store).start(
            "127.0.0.1", None, udp=("127.0.0.1", 0)
        ) as server:
            assert server.udp_address is not None
            url = f"udp://127.0.0.1:{server.udp_address[1]}"
            async with AsyncMaster(
                url, timeout=TIMEOUT, max_in_flight=8, backend=backend.BACKEND
            ) as m:
                got = await asyncio.gather(*(m.read_holding_registers(1, i, 2) for i in range(40)))
                assert got == [[(7 * i + 3) & 0xFFFF, (7 * i + 10) & 0xFFFF] for i in range(40)]
                assert m.counters["responses"] == 40 and m.counters["late"] == 0

    asyncio.run(main())


# -- what is dropped -------------------------------------------------------------------


def test_stale_answers_and_garbage_are_dropped_not_taken(backend: ModuleType) -> None:
    """Before the answer: the answer of another transaction (a stale one), a datagram
    with bytes after its ADU, one cut short, one of protocol id 1, and plain garbage;
    the master takes none of them and returns the real answer."""

    def answer(request: bytes, client: tuple[str, int], sock: socket.socket) -> None:
        tid, unit = struct.unpack(">H", request[:2])[0], request[6]
        good = adu(tid, unit, registers([0x1234]))
        for junk in (
            adu((tid - 1) & 0xFFFF, unit, registers([0xDEAD])),  # a stale transaction
            good + b"\x00",  # an ADU and one byte more
            good[:-1],  # cut short
            adu(tid, unit, registers([0xDEAD]), protocol=1),  # not Modbus
            b"\xff" * 3,
        ):
            sock.sendto(junk, client)
        sock.sendto(good, client)

    with (
        scripted(answer) as server,
        Master(server.url, timeout=TIMEOUT, backend=backend.BACKEND) as m,
    ):
        assert m.read_holding_registers(1, 0, 1) == [0x1234]
        assert m.read_holding_registers(1, 0, 1) == [0x1234]
        counters = m.counters
        assert counters["late"] == 2 and counters["frame_errors"] == 8
        assert counters["responses"] == 2 and counters["timeouts"] == 0

    async def main() -> None:
        with scripted(answer) as server:
            async with AsyncMaster(server.url, timeout=TIMEOUT, backend=backend.BACKEND) as m:
                assert await m.read_holding_registers(1, 0, 1) == [0x1234]
                assert m.counters["late"] == 1 and m.counters["frame_errors"] == 4

    asyncio.run(main())


def test_an_answer_from_another_address_is_not_taken() -> None:
    """A datagram with the right transaction id from another socket (another port of
    the same host) is not the server's answer: the master returns the server's."""
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))

    def answer(request: bytes, client: tuple[str, int], sock: socket.socket) -> None:
        tid, unit = struct.unpack(">H", request[:2])[0], request[6]
        other.sendto(adu(tid, unit, registers([0xBAD0])), client)  # first, from elsewhere
        sock.sendto(adu(tid, unit, registers([0x0600])), client)

    try:
        with scripted(answer) as server, Master(server.url, timeout=TIMEOUT) as m:
            assert m.read_holding_registers(1, 680, 1) == [0x0600]
            assert m.read_holding_registers(1, 680, 1) == [0x0600]

        async def main() -> None:
            with scripted(answer) as server:
                async with AsyncMaster(server.url, timeout=TIMEOUT) as m:
                    assert await m.read_holding_registers(1, 680, 1) == [0x0600]

        asyncio.run(main())
    finally:
        other.close()


def test_the_request_is_one_mbap_datagram() -> None:
    """What the master sends: one datagram, the MBAP header and the PDU ([TCP] 3.1.3),
    a new transaction id per request; unit ids 0..255 as on tcp://."""

    def answer(request: bytes, client: tuple[str, int], sock: socket.socket) -> None:
        tid, unit = struct.unpack(">H", request[:2])[0], request[6]
        sock.sendto(adu(tid, unit, registers([7])), client)

    with scripted(answer) as server, Master(server.url, timeout=TIMEOUT) as m:
        m.read_holding_registers(1, 0x0102, 1)
        m.read_holding_registers(255, 0x0102, 1)
        m.read_holding_registers(0, 0x0102, 1)  # unit 0 reads: the device itself (4.4.1.2)
        first, second, third = server.requests
        body = bytes([3, 0x01, 0x02, 0x00, 0x01])
        assert first[2:] == struct.pack(">HHB", 0, 6, 1) + body
        assert second[2:] == struct.pack(">HHB", 0, 6, 255) + body
        assert third[2:] == struct.pack(">HHB", 0, 6, 0) + body
        tids = [struct.unpack(">H", r[:2])[0] for r in server.requests]
        assert len(set(tids)) == 3


# -- loss and retries ------------------------------------------------------------------


def test_a_lost_request_is_recovered_by_a_retry(pymodbus_udp: int, backend: ModuleType) -> None:
    relay = Relay(pymodbus_udp, drop=1)
    try:
        with Master(relay.url, timeout=TIMEOUT, retries=2, backend=backend.BACKEND) as m:
            assert m.read_holding_registers(1, 40, 4) == pattern.holdings(1, 40, 4)
            assert relay.dropped == 1 and relay.forwarded >= 1
            assert m.counters["timeouts"] >= 1 and m.counters["responses"] == 1
    finally:
        relay.close()

    async def main() -> None:
        relay = Relay(pymodbus_udp, drop=1)
        try:
            async with AsyncMaster(relay.url, timeout=TIMEOUT, retries=2) as m:
                assert await m.read_input_registers(1, 9, 2) == pattern.inputs(1, 9, 2)
                assert relay.dropped == 1 and m.counters["timeouts"] >= 1
        finally:
            relay.close()

    asyncio.run(main())


def test_without_retries_a_lost_request_is_no_response(pymodbus_udp: int) -> None:
    relay = Relay(pymodbus_udp, drop=1)
    try:
        with Master(relay.url, timeout=0.5, retries=0) as m:
            with pytest.raises(NoResponseError, match=r"within 0\.5 s"):
                m.read_holding_registers(1, 0, 1)
            m.timeout = TIMEOUT  # (the next one is answered: the timeout only bounds a failure)
            assert m.read_holding_registers(1, 0, 1) == pattern.holdings(1, 0, 1)
    finally:
        relay.close()


def test_a_closed_port_is_said_at_once_and_retried() -> None:
    """ICMP port unreachable (nothing bound to the port): NoResponseError saying so,
    each retry sent again."""
    url = f"udp://127.0.0.1:{free_udp_port()}"
    with Master(url, timeout=TIMEOUT, retries=2) as m:
        with pytest.raises(NoResponseError, match="port unreachable"):
            m.read_coils(1, 0, 1)
        assert m.counters["requests"] == 3

    async def main() -> None:
        async with AsyncMaster(url, timeout=TIMEOUT, retries=1) as m:
            with pytest.raises(NoResponseError, match="port unreachable"):
                await m.read_coils(1, 0, 1)
            assert m.counters["requests"] == 2

    asyncio.run(main())


# -- bad arguments ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "words"),
    [
        ("udp://", "expected udp://HOST"),
        ("udp://:502", "expected udp://HOST"),
        ("udp://plc:99999", "the port must be 0..65535"),
        ("udp://plc:x", "the port must be 0..65535"),
        ("udp://plc:502/path", "expected udp://HOST"),
    ],
)
def test_bad_urls_are_refused_before_anything_is_sent(url: str, words: str) -> None:
    with pytest.raises(ValueError, match=words) as info:
        Master(url)
    assert url in str(info.value)
    with pytest.raises(ValueError, match=words):
        AsyncMaster(url)


def test_bad_keywords_and_unknown_hosts() -> None:
    with pytest.raises(PortError, match=r"udp://no-such-host\.invalid:502"):
        Master("udp://no-such-host.invalid")
    with pytest.raises(ValueError, match="tls: only an mbaps:// port"):
        Master("udp://127.0.0.1:1", tls=object())
    with pytest.raises(ValueError, match="timeout"):
        Master("udp://127.0.0.1:1", timeout=0)
    with pytest.raises(ValueError, match="max_in_flight"):
        Master("udp://127.0.0.1:1", max_in_flight=2)  # the blocking master: one at a time

    async def main() -> None:
        m = AsyncMaster("udp://no-such-host.invalid:5020", timeout=TIMEOUT)
        with pytest.raises(PortError, match=r"udp://no-such-host\.invalid:5020"):
            await m.read_coils(1, 0, 1)

    asyncio.run(main())
