"""What the TCP server asks of its application: `execute`, guarded by the application
itself (no private attribute read), answers as bytes (exception answers too) and
silence as None, and the MBAP fields of each request copied into its answer."""

from __future__ import annotations

import asyncio
import inspect
import socket
import threading

from ptylink import make_store

import pyrtu.tcp.server
from pyrtu import Slave, encode_mbap, parse_tcp_stream
from pyrtu.tcp.server import LocalBus, TcpServer


class Silent:
    """Answers FC 03 with exception 2 and stays silent for anything else."""

    addresses = frozenset({7})

    def execute(self, unit: int, request: bytes) -> bytes | None:
        return bytes((0x83, 2)) if request[0] == 3 else None


def test_local_bus_answers_bytes_and_silence_without_exceptions() -> None:
    bus = LocalBus(Silent())
    assert asyncio.run(bus.request(7, bytes.fromhex("03 0000 0001"))) == b"\x83\x02"
    assert asyncio.run(bus.request(7, bytes.fromhex("06 0000 0001"))) is None
    assert asyncio.run(bus.request(0, bytes.fromhex("03 0000 0001"))) is None  # broadcast


def test_the_server_reads_no_private_attribute_of_its_application() -> None:
    assert "_guard" not in inspect.getsource(pyrtu.tcp.server)


def test_a_sync_slave_executes_under_its_lock() -> None:
    """A Slave served on TCP as well: a request from the TCP side waits while the
    serial side holds the lock (it runs the protocol, which executes requests)."""
    with Slave("loop://", store=make_store(), parity="N") as slave:
        done = threading.Event()
        answer: list[bytes | None] = []

        def execute() -> None:
            answer.append(slave.execute(1, bytes.fromhex("03 0000 0001")))
            done.set()

        with slave._lock:
            worker = threading.Thread(target=execute)
            worker.start()
            assert not done.wait(0.2)  # (waits for the lock however long it is held)
        assert done.wait(5.0)
        worker.join()
        assert answer == [bytes.fromhex("03 02 03E8")]


def test_answers_carry_the_request_fields_and_silence_is_0x0b() -> None:
    async def main() -> list[tuple[int, int, int, bytes]]:
        async with await TcpServer(Silent()).start("127.0.0.1", 0) as server:
            assert server.address is not None
            reader, writer = await asyncio.open_connection(*server.address)
            sock = writer.get_extra_info("socket")
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            writer.write(encode_mbap(0xBEEF, 7, bytes.fromhex("03 0000 0001")))
            writer.write(encode_mbap(0x0102, 0xFF, bytes.fromhex("06 0000 0001")))
            data = b""
            while len(parse_tcp_stream(data, "master")) < 2:
                data += await asyncio.wait_for(reader.read(512), 5.0)
            writer.close()
            return [(f.transaction, f.protocol, f.unit, f.pdu) for f in parse_tcp_stream(data)]

    assert asyncio.run(main()) == [
        (0xBEEF, 0, 7, b"\x83\x02"),  # the application's exception answer, as it is
        (0x0102, 0, 0xFF, b"\x86\x0b"),  # its silence: gateway target failed to respond
    ]
