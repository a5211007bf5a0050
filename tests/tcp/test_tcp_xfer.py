"""The blocking Modbus TCP client's transaction in one call (C: csrc/rtu_tcp_io.c;
the twin: pyrtu/drivers/_pyxfer.py TcpXferRunner), on both backends, against a
scripted server on 127.0.0.1 that answers each request with chosen bytes, in chosen
TCP segments: the boundaries of the MBAP framing (Messaging on TCP/IP
Implementation Guide V1.0b, 3.1.3: the length field is the only delimiter; 2..254),
stale answers, wrong units and functions, a connection closed mid-answer, the
timeout.  Every expected value is built here with `struct` from the guide's header
layout, never by the code under test; both backends must give the same results,
counters and error messages."""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from types import ModuleType

import pytest
from c_core import needs_c
from hypothesis import given, settings
from hypothesis import strategies as st
from waiting import wait_for

import pyrtu
from pyrtu import ExceptionResponseError, Master, NoResponseError, PortError
from pyrtu.drivers import _pyxfer
from pyrtu.drivers.xfer import TcpScan
from pyrtu.pdu.errors import FrameError
from pyrtu.tcp.client import TcpClient

#: one step of a scripted answer: bytes sent as a segment of their own, a pause
#: (seconds), or None: close the connection
Step = bytes | float | None
Script = Callable[[bytes], list[Step]]

READ = bytes.fromhex("03 00 00 00 02")  # FC 03, address 0, 2 registers
ANSWER_PDU = bytes.fromhex("03 04 00 2a 00 2b")
#: the pause between segments: with TCP_NODELAY each send is a segment of its own,
#: and the client has read the last one before the next is sent
GAP = 0.003


def adu(tid: int, unit: int, pdu: bytes, *, protocol: int = 0, length: int | None = None) -> bytes:
    """An MBAP ADU (3.1.3: transaction id, protocol id, length = 1 + PDU, unit id)."""
    n = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", tid, protocol, n, unit) + pdu


def tid_of(request: bytes) -> int:
    return int(struct.unpack(">H", request[:2])[0])


class ScriptedServer:
    """Accepts connections on 127.0.0.1; reads each request whole (by its length
    field) and carries out ``script(request)``."""

    def __init__(self, script: Script) -> None:
        self.script = script
        self.requests: list[bytes] = []
        self.listener = socket.socket()
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(4)
        self.url = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        self.failures: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            while True:
                try:
                    conn, _ = self.listener.accept()
                except OSError:
                    return
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with conn:
                    self._serve(conn)
        except BaseException as exc:  # reported by close(): a test fails on it
            self.failures.append(exc)

    def _read(self, conn: socket.socket, n: int) -> bytes | None:
        data = b""
        while len(data) < n:
            chunk = conn.recv(n - len(data))
            if not chunk:
                return None
            data += chunk
        return data

    def _serve(self, conn: socket.socket) -> None:
        while True:
            head = self._read(conn, 7)
            if head is None:
                return
            rest = self._read(conn, struct.unpack(">H", head[4:6])[0] - 1)
            if rest is None:
                return
            request = head + rest
            self.requests.append(request)
            for step in self.script(request):
                if step is None:
                    return
                if isinstance(step, float):
                    time.sleep(step)
                else:
                    conn.sendall(step)
                    time.sleep(GAP)

    def close(self) -> None:
        self.listener.close()
        assert not self.failures, self.failures


@pytest.fixture
def serve() -> Iterator[Callable[[Script], ScriptedServer]]:
    servers: list[ScriptedServer] = []

    def start(script: Script) -> ScriptedServer:
        servers.append(ScriptedServer(script))
        return servers[-1]

    yield start
    for s in servers:
        s.close()


def client(server: ScriptedServer, backend: ModuleType, timeout: float = 2.0) -> TcpClient:
    return TcpClient(server.url, timeout=timeout, backend=getattr(backend, "BACKEND", "python"))


def answering(*steps: Callable[[int], Step]) -> Script:
    """A script of steps built from the request's transaction id."""
    return lambda request: [step(tid_of(request)) for step in steps]


# ------------------------------------------------------------------ answers whole


def test_an_answer_split_into_single_bytes_is_read_whole(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    def script(request: bytes) -> list[Step]:
        return [bytes((b,)) for b in adu(tid_of(request), 1, ANSWER_PDU)]

    server = serve(script)
    with client(server, backend) as c:
        assert c.request(1, READ) == ANSWER_PDU
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["responses"] == 2 and c.counters["late"] == 0
    assert server.requests == [adu(1, 1, READ), adu(2, 1, READ)]  # ids 1, 2: 3.1.3


def test_a_stale_answer_then_the_right_one(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    stale = bytes.fromhex("03 04 de ad be ef")
    server = serve(answering(lambda t: adu(t - 1, 1, stale), lambda t: adu(t, 1, ANSWER_PDU)))
    with client(server, backend) as c:
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 1 and c.counters["responses"] == 1


def test_two_answers_in_one_segment(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    """A stale answer and the right one in one segment, then the right one and a
    duplicate after it: every whole ADU read is resolved in the same call."""
    server = serve(
        lambda r: (
            [adu(tid_of(r) - 1, 1, b"\x03\x02\x00\x00") + adu(tid_of(r), 1, ANSWER_PDU)]
            if tid_of(r) == 1
            else [adu(tid_of(r), 1, ANSWER_PDU) * 2]
        )
    )
    with client(server, backend) as c:
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 1
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 2 and c.counters["responses"] == 2


def test_more_late_answers_than_the_buffer_holds(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    """700 stale answers (9,100 bytes, more than TCP_CAPACITY) before the right one,
    in one write: the buffer drops the resolved ones as it fills, every one counted."""
    stale = adu(0xFFFF, 1, ANSWER_PDU)
    server = serve(answering(lambda t: stale * 700 + adu(t, 1, ANSWER_PDU)))
    with client(server, backend) as c:
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 700 and c.counters["responses"] == 1
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 1400


def test_a_partial_answer_at_the_timeout_is_late_in_the_next_call(  # type: ignore[no-untyped-def]
    backend: ModuleType, serve
) -> None:
    """The first answer's head comes before the timeout and its rest after it: the
    next transaction completes it, drops it as late and reads its own answer."""
    timeout = 0.2

    def script(request: bytes) -> list[Step]:
        tid = tid_of(request)
        whole = adu(tid, 1, ANSWER_PDU)
        if tid == 1:
            return [whole[:5], timeout * 2, whole[5:]]
        return [whole]

    server = serve(script)
    with client(server, backend, timeout=timeout) as c:
        with pytest.raises(NoResponseError):
            c.request(1, READ)
        c.timeout = 2.0
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["timeouts"] == 1 and c.counters["late"] == 1


def test_the_longest_answer_length_254(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    """Length 254 (unit + a PDU of 253 bytes, the most 3.1.3 allows) is an answer."""
    pdu = bytes((0x03, 252)) + bytes(range(251))
    assert len(pdu) == 253
    server = serve(answering(lambda t: adu(t, 1, pdu)))
    with client(server, backend) as c:
        assert c.request(1, READ) == pdu


# ------------------------------------------------------------------ errors


@pytest.mark.parametrize(
    ("header", "reason"),
    [
        ({"length": 0}, "length"),
        ({"length": 1}, "length"),
        ({"length": 255}, "length"),
        ({"length": 0xFFFF}, "length"),
        ({"protocol": 1}, "protocol_id"),
    ],
)
def test_a_malformed_header_ends_the_connection(  # type: ignore[no-untyped-def]
    backend: ModuleType, serve, header: dict[str, int], reason: str
) -> None:
    server = serve(answering(lambda t: adu(t, 1, ANSWER_PDU, **header)))
    with client(server, backend) as c:
        with pytest.raises(FrameError) as info:
            c.request(1, READ)
        assert str(info.value) == f"bad MBAP header from the server ({reason})"
        with pytest.raises(PortError, match="the connection is unusable: bad MBAP header"):
            c.request(1, READ)
        assert c.counters["requests"] == 1  # nothing sent the second time


def test_a_malformed_header_after_the_answer(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    server = serve(answering(lambda t: adu(t, 1, ANSWER_PDU) + adu(t, 1, b"\x03", length=1)))
    with client(server, backend) as c:
        assert c.request(1, READ) == ANSWER_PDU
        with pytest.raises(
            PortError, match=r"unusable: bad MBAP header from the server \(length\)"
        ):
            c.request(1, READ)


@pytest.mark.parametrize(
    ("unit", "pdu", "message"),
    [
        (2, ANSWER_PDU, "answer to unit 1 function 3 came back as unit 2 function 3"),
        (1, b"\x04" + ANSWER_PDU[1:], "answer to unit 1 function 3 came back as unit 1 function 4"),
        (1, b"\x84\x02", "answer to unit 1 function 3 came back as unit 1 function 132"),
    ],
)
def test_a_wrong_unit_or_function(  # type: ignore[no-untyped-def]
    backend: ModuleType, serve, unit: int, pdu: bytes, message: str
) -> None:
    def script(request: bytes) -> list[Step]:
        tid = tid_of(request)
        right = adu(tid, 1, ANSWER_PDU)
        return [adu(tid, unit, pdu), right] if tid == 1 else [right]

    server = serve(script)
    with client(server, backend) as c:
        with pytest.raises(FrameError) as info:
            c.request(1, READ)
        assert str(info.value) == message
        assert c.counters["frame_errors"] == 1
        # the connection goes on (the server's second ADU is late for the next one)
        assert c.request(1, READ) == ANSWER_PDU
        assert c.counters["late"] == 1


def test_exception_answers(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    replies = iter([b"\x83\x02", b"\x83\x02", b"\x83\x02\x00"])
    server = serve(answering(lambda t: adu(t, 1, next(replies))))
    with client(server, backend) as c:
        with pytest.raises(ExceptionResponseError) as info:
            c.request(1, READ)
        assert (info.value.slave, info.value.function, info.value.code) == (1, 3, 2)
        assert c.request(1, READ, raw=True) == b"\x83\x02"
        with pytest.raises(FrameError, match="exception response of 3 bytes"):
            c.request(1, READ)
        assert c.counters["exceptions"] == 3 and c.counters["frame_errors"] == 1


@pytest.mark.parametrize("cut", [0, 3, 7, 9])
def test_the_connection_closed_mid_answer(backend: ModuleType, serve, cut: int) -> None:  # type: ignore[no-untyped-def]
    server = serve(answering(lambda t: adu(t, 1, ANSWER_PDU)[:cut] or 0.0, lambda t: None))
    with client(server, backend) as c:
        with pytest.raises(PortError) as info:
            c.request(1, READ)
        assert str(info.value) == f"{server.url}: the server closed the connection"
        with pytest.raises(PortError, match="the connection is unusable"):
            c.request(1, READ)


def test_a_broadcast_reads_nothing(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    server = serve(lambda request: [])
    with client(server, backend) as c:
        assert c.request(0, bytes.fromhex("06 00 01 00 07")) is None
        assert c.counters["broadcasts"] == 1
        asyncio.run(wait_for(lambda: bool(server.requests), "the broadcast at the server", 10.0))
    assert server.requests == [adu(1, 0, bytes.fromhex("06 00 01 00 07"))]


def test_a_closed_client(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    server = serve(answering(lambda t: adu(t, 1, ANSWER_PDU)))
    c = client(server, backend)
    c.close()
    with pytest.raises(PortError, match=r"send failed: \[Errno 9\] Bad file descriptor"):
        c.request(1, READ)


@pytest.mark.wall_clock  # bounded by the timeout and half of it
@pytest.mark.parametrize("timeout", [0.05, 0.2])
def test_the_timeout_exactly(backend: ModuleType, serve, timeout: float) -> None:  # type: ignore[no-untyped-def]
    server = serve(lambda request: [])
    with client(server, backend, timeout=timeout) as c:
        start = time.monotonic()
        with pytest.raises(NoResponseError) as info:
            c.request(1, READ)
        waited = time.monotonic() - start
    assert str(info.value) == f"no answer from unit 1 (function 3) within {timeout} s"
    assert timeout <= waited < timeout * 1.5
    assert c.counters["timeouts"] == 1


def test_master_retries_and_logs_the_same(  # type: ignore[no-untyped-def]
    backend: ModuleType, serve, caplog: pytest.LogCaptureFixture
) -> None:
    """Through `Master` (its retries on a timeout): the first request unanswered,
    the retry answered after a stale answer; -vv's lines as the event path wrote them."""

    def script(request: bytes) -> list[Step]:
        tid = tid_of(request)
        return [] if tid == 1 else [adu(tid - 1, 1, ANSWER_PDU), adu(tid, 1, ANSWER_PDU)]

    server = serve(script)
    m = Master(server.url, timeout=0.3, retries=1, backend=getattr(backend, "BACKEND", "python"))
    runner = m._conn._client._runner  # type: ignore[union-attr]
    assert type(runner).__module__ == (  # the master's backend= picks the runner
        "pyrtu.drivers._cxfer"
        if getattr(backend, "BACKEND", "") == "c"
        else "pyrtu.drivers._pyxfer"
    )
    with m, caplog.at_level(logging.DEBUG, logger="pyrtu.drivers.master"):
        assert m.read_holding_registers(1, 0, 2) == [42, 43]
        assert m.counters["timeouts"] == 1 and m.counters["late"] == 1
    lines = [r.getMessage() for r in caplog.records if r.name == "pyrtu.drivers.master"]
    hexed = [
        adu(t, 1, p).hex(" ") for t, p in ((1, READ), (2, READ), (1, ANSWER_PDU), (2, ANSWER_PDU))
    ]
    assert lines[0] == f"TX unit 1 fc 3 tid 1: {hexed[0]}"
    assert lines[1] == f"TX unit 1 fc 3 tid 2: {hexed[1]}"
    assert lines[2] == f"RX late (no request tid 1 in flight), dropped: {hexed[2]}"
    assert lines[3].startswith(f"RX unit 1 fc 3 tid 2: {hexed[3]} (") and lines[3].endswith(" ms)")
    assert len(lines) == 4


# ------------------------------------------------------------------ the scan


def _c_scan(data: bytes, tid: int) -> TcpScan:
    from pyrtu.core._rtu_core import ffi, lib

    s = ffi.new("rtu_tcp_scan_result *")
    assert lib.rtu_tcp_scan(data, len(data), tid, s) == lib.RTU_OK
    return TcpScan(s.used, s.ans_off, s.ans_len, s.late, s.late_after, s.error)


_frames = st.lists(
    st.one_of(
        st.builds(adu, st.integers(0, 3), st.integers(0, 255), st.binary(min_size=1, max_size=20)),
        st.binary(max_size=12),
    ),
    max_size=6,
)


@needs_c("c" not in pyrtu.available_backends(), "compares the C scan with its twin")
@settings(max_examples=400, deadline=None)
@given(frames=_frames, tid=st.integers(0, 3))
def test_the_c_scan_and_its_twin_agree(frames: list[bytes], tid: int) -> None:
    data = b"".join(frames)
    ours = _pyxfer.tcp_scan(data, len(data), tid, TcpScan())
    assert _c_scan(data, tid) == ours
    assert ours.used <= len(data) and ours.late_after <= ours.late


def test_the_scan_by_the_guide() -> None:
    """Expected values counted by hand from 3.1.3's layout."""
    a, b = adu(7, 1, READ), adu(8, 1, ANSWER_PDU)
    data = a + b + a + b"\x00\x09\x00"
    assert _pyxfer.tcp_scan(data, len(data), 8, TcpScan()) == TcpScan(
        used=2 * len(a) + len(b), ans_off=len(a), ans_len=len(b), late=2, late_after=1
    )
    bad = adu(8, 1, READ, length=255)
    assert _pyxfer.tcp_scan(a + bad, len(a + bad), 8, TcpScan()) == TcpScan(
        used=len(a), late=1, error=2
    )


# ------------------------------------------------------------------ signals


def test_a_signal_during_the_wait(backend: ModuleType, serve) -> None:  # type: ignore[no-untyped-def]
    """A signal's handler runs during the wait (C: the call returns, Python runs the
    handler, the wait goes on to the same deadline); one that raises ends it."""
    import signal

    seen: list[int] = []

    def note(signum: int, frame: object) -> None:
        seen.append(signum)

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    server = serve(answering(lambda t: 0.3, lambda t: adu(t, 1, ANSWER_PDU)))
    old = signal.signal(signal.SIGALRM, note)
    try:
        with client(server, backend) as c:
            signal.setitimer(signal.ITIMER_REAL, 0.05)
            assert c.request(1, READ) == ANSWER_PDU
            assert seen == [signal.SIGALRM]
            signal.signal(signal.SIGALRM, stop)
            signal.setitimer(signal.ITIMER_REAL, 0.05)
            with pytest.raises(KeyboardInterrupt):
                c.request(1, READ)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
