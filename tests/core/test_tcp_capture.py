"""`parse_tcp_stream` on a real TCP capture: the two directions of a libmodbus TCP
client talking to a libmodbus TCP server, recorded by a relay on 127.0.0.1 (every
byte of the capture written by a third-party peer), parsed on both backends."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from types import ModuleType

import pytest
from peers import pattern
from peers.tools import PeerBinaries, free_tcp_port, libmodbus_script, libmodbus_server

from pyrtu import pdu
from pyrtu.core.frames import FrameKind

pytest_plugins = ["peers.fixtures"]


class Recorder:
    """Relays one TCP connection to ``upstream`` and keeps each direction's bytes."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = self.listener.getsockname()[:2]
        self.requests = bytearray()  # client -> server
        self.answers = bytearray()  # server -> client
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        client, _ = self.listener.accept()
        server = socket.create_connection(self.upstream)
        pumps = [
            threading.Thread(target=self._pump, args=(client, server, self.requests)),
            threading.Thread(target=self._pump, args=(server, client, self.answers)),
        ]
        for t in pumps:
            t.start()
        for t in pumps:
            t.join()
        client.close()
        server.close()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket, into: bytearray) -> None:
        while True:
            try:
                chunk = src.recv(65536)
            except OSError:
                chunk = b""
            if not chunk:
                try:
                    dst.shutdown(socket.SHUT_WR)
                except OSError:
                    pass
                return
            into += chunk
            dst.sendall(chunk)

    def join(self) -> None:
        self._thread.join(30)
        self.listener.close()
        assert not self._thread.is_alive()


@pytest.fixture
def capture(peer_binaries: PeerBinaries) -> Iterator[tuple[bytes, bytes]]:
    port = free_tcp_port()
    with libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1):
        rec = Recorder(("127.0.0.1", port))
        host, relay = rec.address
        ops = ["r03:0:10", "r01:5:30", "w16:300:1,2,3", "r03:300:3", "r04:7:4", "r03:60000:1",
               "w06:40:77", "r02:0:16"]  # fmt: skip
        results = libmodbus_script(peer_binaries, f"tcp:{host}:{relay}", 1, ops, timeout_ms=2000)
        assert results[0]["values"] == pattern.holdings(1, 0, 10)
        rec.join()
        yield bytes(rec.requests), bytes(rec.answers)


def test_parse_a_recorded_tcp_conversation(
    backend: ModuleType, capture: tuple[bytes, bytes]
) -> None:
    requests, answers = capture
    asked = backend.parse_tcp_stream(requests, "slave")
    told = backend.parse_tcp_stream(answers, "master")
    assert not list(asked.errors()) and not list(told.errors())
    assert len(asked) == len(told) == 8
    # libmodbus numbers its transactions; each answer carries its request's id and unit
    assert [f.transaction for f in told] == [f.transaction for f in asked]
    assert len({f.transaction for f in asked}) == 8
    assert {f.unit for f in asked} == {f.unit for f in told} == {1}
    assert [f.kind for f in asked] == [FrameKind.REQUEST] * 8
    assert [f.kind for f in told].count(FrameKind.EXCEPTION) == 1
    assert asked[0].pdu == pdu.read_request(3, 0, 10)
    assert pdu.parse_registers(told[0].pdu, 10) == pattern.holdings(1, 0, 10)
    assert pdu.parse_registers(told[3].pdu, 3) == [1, 2, 3]
    assert (told[5].function, told[5].exception_code) == (0x83, 2)
    # every byte accounted for, at the offsets of the stream
    assert sum(len(f.adu) for f in told) == len(answers)
    assert [f.offset for f in told] == [sum(len(g.adu) for g in told[:i]) for i in range(len(told))]
    assert told.counters["response"] == 7 and told.counters["exception"] == 1


def test_the_framer_fed_the_capture_byte_by_byte_finds_the_same(
    backend: ModuleType, capture: tuple[bytes, bytes]
) -> None:
    _, answers = capture
    f = backend.MbapFramer("master")
    for i in range(len(answers)):
        f.receive_data(answers[i : i + 1])
    f.receive_data(b"")
    framed = [(e.transaction, e.adu) for e in f.events()]
    assert framed == [(e.transaction, e.adu) for e in backend.parse_tcp_stream(answers, "master")]
