"""The asyncio Modbus TCP client's reads (issue 30.1): the socket is read into the
scanner's buffer (the one answer awaited, alone in a read, told by its header; any
other read scanned, C: rtu_tcp_scan; the twin), on both backends, against
scripted servers on 127.0.0.1 that cut, join and spoil the answers' bytes.  The
expected bytes are built with `struct` from the MBAP layout (Messaging on TCP/IP
Implementation Guide V1.0b, 3.1.3), not by pyrtu."""

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

from pyrtu import ExceptionResponseError, FrameError, NoResponseError, PortError
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.tcp import AsyncTcpClient

READ = struct.pack(">BHH", 3, 0, 2)  # FC 03, address 0, 2 registers
VALUES = struct.pack(">BBHH", 3, 4, 0x1234, 0xABCD)  # its response PDU


def adu(tid: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def read_requests(conn: socket.socket, count: int) -> list[tuple[int, int, bytes]]:
    """``count`` whole request ADUs: (transaction id, unit, PDU) each."""
    out = []
    data = b""
    while len(out) < count:
        while len(data) < 6 or len(data) < 6 + struct.unpack(">H", data[4:6])[0]:
            chunk = conn.recv(4096)
            assert chunk, "the client closed the connection"
            data += chunk
        end = 6 + struct.unpack(">H", data[4:6])[0]
        tid, _, _, unit = struct.unpack(">HHHB", data[:7])
        out.append((tid, unit, data[7:end]))
        data = data[end:]
    return out


async def connect(port: int, backend: ModuleType, max_in_flight: int = 1) -> AsyncTcpClient:
    """A client of the scripted server on ``port``, on ``backend``'s core (a 2 s
    timeout: a safety net, never a measurement)."""
    return await AsyncTcpClient.connect(
        f"tcp://127.0.0.1:{port}", timeout=2.0, max_in_flight=max_in_flight,
        backend=backend.BACKEND,
    )  # fmt: skip


@pytest.fixture
def scripted() -> Iterator[Callable[[Callable[[socket.socket], None]], int]]:
    """``start(script)``: a server on a free port whose one connection ``script``
    runs in a thread; its port.  Errors in the script fail the test."""
    listeners: list[socket.socket] = []
    threads: list[threading.Thread] = []
    errors: list[BaseException] = []

    def start(script: Callable[[socket.socket], None]) -> int:
        listener = socket.socket()
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        listeners.append(listener)

        def run() -> None:
            try:
                conn, _ = listener.accept()
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with conn:
                    script(conn)
            except BaseException as exc:  # reported by the fixture
                errors.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        threads.append(thread)
        return int(listener.getsockname()[1])

    yield start
    for listener in listeners:
        listener.close()
    for thread in threads:
        thread.join(10)
    assert not errors, errors


def test_an_answer_cut_anywhere_and_late_answers_before_it(
    backend: ModuleType,
    scripted: Callable[[Callable[[socket.socket], None]], int],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Late ADUs and the answer in one write, then an answer cut at every place of
    its header and PDU (each piece its own read): each read gets what it can."""
    answer_len = 7 + len(VALUES)
    cuts = list(range(1, answer_len))

    def script(conn: socket.socket) -> None:
        ((tid, unit, _),) = read_requests(conn, 1)
        late = adu(tid ^ 0x8000, unit, VALUES) + adu(tid ^ 0x4000, unit, b"\x83\x02")
        conn.sendall(late + adu(tid, unit, VALUES))
        for cut in cuts:
            ((tid, unit, _),) = read_requests(conn, 1)
            whole = adu(tid, unit, VALUES)
            conn.sendall(whole[:cut])
            time.sleep(0.01)  # (TCP_NODELAY: the first piece is read by itself)
            conn.sendall(whole[cut:])
        read_requests(conn, 1)  # the last one goes unanswered: a late answer after it
        conn.sendall(adu(0xFFFF, 1, VALUES)[:3])
        conn.recv(1)  # until the client closes

    port = scripted(script)

    async def main() -> None:
        c = await connect(port, backend)
        async with c:
            for _ in range(1 + len(cuts)):
                assert await c.request(1, READ) == VALUES
            assert c.counters["late"] == 2 and c.counters["responses"] == 1 + len(cuts)
            c.timeout = 0.3
            with pytest.raises(NoResponseError, match="no answer from unit 1"):
                await c.request(1, READ)

    with caplog.at_level(logging.DEBUG, logger="pyrtu.drivers.master"):
        asyncio.run(main())
    late_lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("RX late")]
    assert len(late_lines) == 2
    rx = [r.getMessage() for r in caplog.records if r.getMessage().startswith("RX unit 1 fc 3")]
    assert len(rx) == 1 + len(cuts) and adu(1, 1, VALUES).hex(" ")[5:] in rx[0]


def test_pipelined_answers_in_one_read_in_any_order(
    backend: ModuleType, scripted: Callable[[Callable[[socket.socket], None]], int]
) -> None:
    """Four requests on the wire, their answers back in reverse order in one write,
    one of them an exception response and one for another unit (a frame error)."""

    def script(conn: socket.socket) -> None:
        requests = read_requests(conn, 4)
        replies = []
        for i, (tid, unit, pdu) in enumerate(requests):
            assert pdu == READ
            if i == 1:
                replies.append(adu(tid, unit, b"\x83\x02"))
            elif i == 2:
                replies.append(adu(tid, unit + 1, VALUES))
            else:
                replies.append(adu(tid, unit, struct.pack(">BBHH", 3, 4, i, unit)))
        conn.sendall(b"".join(reversed(replies)))
        conn.recv(1)  # until the client closes

    port = scripted(script)

    async def main() -> None:
        c = await connect(port, backend, 4)
        async with c:
            got = await asyncio.gather(
                *(c.request(unit, READ) for unit in (5, 6, 7, 8)), return_exceptions=True
            )
        assert got[0] == struct.pack(">BBHH", 3, 4, 0, 5)
        assert isinstance(got[1], ExceptionResponseError) and got[1].code == 2
        assert "came back as unit 8" in str(got[2])
        assert got[3] == struct.pack(">BBHH", 3, 4, 3, 8)
        assert c.counters == {
            "requests": 4,
            "responses": 2,
            "broadcasts": 0,
            "exceptions": 1,
            "timeouts": 0,
            "frame_errors": 1,
            "late": 0,
        }

    asyncio.run(main())


def test_a_bad_header_after_the_answer_ends_the_connection(
    backend: ModuleType, scripted: Callable[[Callable[[socket.socket], None]], int]
) -> None:
    """The answer, then a header with protocol id 1, in one write: the answer is the
    result; the stream is lost from there and the next request says why."""

    def script(conn: socket.socket) -> None:
        ((tid, unit, _),) = read_requests(conn, 1)
        conn.sendall(adu(tid, unit, VALUES) + adu(tid + 1, unit, VALUES, protocol=1))
        conn.recv(1)  # until the client closes

    port = scripted(script)

    async def main() -> None:
        c = await connect(port, backend)
        async with c:
            assert await c.request(1, READ) == VALUES

            async def broken() -> None:  # (the bad header may come in a read of its own)
                while c._proto.broken is None:
                    await asyncio.sleep(0.01)

            await asyncio.wait_for(broken(), 10.0)
            with pytest.raises(PortError, match=r"unusable: bad MBAP header .*protocol"):
                await c.request(1, READ)

    asyncio.run(main())


USER_FC = 0x41  # a user-defined function code (Application Protocol 5): any PDU back


def test_an_answer_alone_in_a_read_at_the_header_limits(
    backend: ModuleType, scripted: Callable[[Callable[[socket.socket], None]], int]
) -> None:
    """Answers each alone in a read (the client tells them by their header, without
    a scan): a 253-byte PDU (length field 254, the most, 3.1.3) is the answer; a
    lone ADU of another transaction is late (dropped, counted) and the answer after
    it, alone too, is the result; a 1-byte PDU (length 2, the least) is one too."""
    longest = bytes([USER_FC]) + bytes(range(252))

    def script(conn: socket.socket) -> None:
        ((tid, unit, pdu),) = read_requests(conn, 1)
        assert pdu == bytes([USER_FC])
        conn.sendall(adu(tid, unit, longest))
        ((tid, unit, _),) = read_requests(conn, 1)
        conn.sendall(adu(tid ^ 1, unit, VALUES))
        time.sleep(0.05)  # (TCP_NODELAY: read by itself, as a rule; either way late)
        conn.sendall(adu(tid, unit, VALUES))
        ((tid, unit, _),) = read_requests(conn, 1)
        conn.sendall(adu(tid, unit, bytes([USER_FC])))
        conn.recv(1)  # until the client closes

    port = scripted(script)

    async def main() -> None:
        c = await connect(port, backend)
        async with c:
            assert len(adu(0, 1, longest)) == 6 + 254
            assert await c.request(1, bytes([USER_FC])) == longest
            assert await c.request(1, READ) == VALUES
            assert await c.request(1, bytes([USER_FC])) == bytes([USER_FC])
            assert c.counters["late"] == 1 and c.counters["responses"] == 3

    asyncio.run(main())


@pytest.mark.parametrize(
    ("spoil", "reason"),
    [
        (lambda tid: adu(tid, 1, VALUES, protocol=1), "protocol"),
        (lambda tid: adu(tid, 1, bytes([USER_FC]) + bytes(253)), "length"),  # length 255
        (lambda tid: adu(tid, 1, b""), "length"),  # length 1: a unit id, no PDU
    ],
    ids=["protocol id 1", "length 255", "length 1"],
)
def test_a_bad_header_alone_in_a_read_ends_the_connection(
    backend: ModuleType,
    scripted: Callable[[Callable[[socket.socket], None]], int],
    spoil: Callable[[int], bytes],
    reason: str,
) -> None:
    """The awaited transaction id on a header the guide does not allow (3.1.3:
    protocol id 0; length 2..254), its bytes all in one read: not an answer; the
    request fails with the bad header and the connection is unusable."""

    def script(conn: socket.socket) -> None:
        ((tid, _, _),) = read_requests(conn, 1)
        conn.sendall(spoil(tid))
        conn.recv(1)  # until the client closes

    port = scripted(script)

    async def main() -> None:
        c = await connect(port, backend)
        async with c:
            with pytest.raises(FrameError, match=f"bad MBAP header .*{reason}"):
                # (bounded: a header taken for an answer could leave the await hanging)
                await asyncio.wait_for(c.request(1, bytes([USER_FC])), 10.0)
            with pytest.raises(PortError, match=f"unusable: bad MBAP header .*{reason}"):
                await c.request(1, READ)
            assert c.counters["responses"] == 0 and c.counters["late"] == 0

    asyncio.run(main())


@pytest.mark.wall_clock  # bounded by the shortened timeout, far under the first one
def test_a_shortened_timeout_is_kept_after_answered_requests(
    scripted: Callable[[Callable[[socket.socket], None]], int],
) -> None:
    """An answered request leaves its timer (at 30 s) armed; a request with a
    0.2 s timeout after it must still time out at 0.2 s."""

    def script(conn: socket.socket) -> None:
        ((tid, unit, _),) = read_requests(conn, 1)
        conn.sendall(adu(tid, unit, VALUES))
        read_requests(conn, 1)  # never answered
        conn.recv(1)

    port = scripted(script)

    async def main() -> float:
        c = await AsyncTcpClient.connect(f"tcp://127.0.0.1:{port}", timeout=30.0)
        async with c:
            assert await c.request(1, READ) == VALUES
            c.timeout = 0.2
            t0 = time.monotonic()
            with pytest.raises(NoResponseError):
                await c.request(1, READ)
            return time.monotonic() - t0

    elapsed = asyncio.run(main())
    assert 0.2 <= elapsed < 10.0


def test_async_master_reads_with_its_backends_scan(
    backend: ModuleType, scripted: Callable[[Callable[[socket.socket], None]], int]
) -> None:
    """``AsyncMaster(backend=...)`` over tcp:// scans with that backend (C:
    rtu_tcp_scan; python: the twin), reading into a buffer of its own."""
    from pyrtu.drivers import _pyxfer

    def script(conn: socket.socket) -> None:
        for _ in range(3):
            ((tid, unit, pdu),) = read_requests(conn, 1)
            assert pdu == READ
            conn.sendall(adu(tid, unit, VALUES))
        conn.recv(1)

    port = scripted(script)

    async def main() -> None:
        async with AsyncMaster(
            f"tcp://127.0.0.1:{port}", timeout=2.0, backend=backend.BACKEND
        ) as m:
            for _ in range(3):
                assert await m.read_holding_registers(1, 0, 2) == [0x1234, 0xABCD]
            conn = m._tcp._client._conn  # type: ignore[union-attr]
            assert isinstance(conn, asyncio.BufferedProtocol)
            twin = isinstance(conn.scan.__self__, _pyxfer.TcpScanner)  # type: ignore[attr-defined]
            assert twin == (backend.BACKEND == "python")

    asyncio.run(main())


def test_requests_wait_their_turn_and_a_cancelled_one_is_never_sent(
    scripted: Callable[[Callable[[socket.socket], None]], int],
) -> None:
    """``max_in_flight=1``: a second and third request wait for the first's answer;
    the second, cancelled while it waits, never goes out; the third does."""
    seen: list[int] = []

    def script(conn: socket.socket) -> None:
        for _ in range(2):
            ((tid, unit, _),) = read_requests(conn, 1)
            seen.append(unit)
            conn.sendall(adu(tid, unit, VALUES))
        conn.recv(1)

    port = scripted(script)

    async def main() -> None:
        c = await AsyncTcpClient.connect(f"tcp://127.0.0.1:{port}", timeout=2.0, max_in_flight=1)
        async with c:
            first = asyncio.ensure_future(c.request(1, READ))
            second = asyncio.ensure_future(c.request(2, READ))
            third = asyncio.ensure_future(c.request(3, READ))
            await asyncio.sleep(0)  # all three started: the first on the wire
            second.cancel()
            assert await first == VALUES and await third == VALUES
            with pytest.raises(asyncio.CancelledError):
                await second
            assert c.counters["requests"] == 2

    asyncio.run(main())
    assert seen == [1, 3]


def test_a_turn_handed_to_a_cancelled_waiter_passes_on() -> None:
    """The window of turns: a waiter cancelled after `release` handed it the turn
    (before it ran) passes the turn on, so no turn is lost."""
    from pyrtu.tcp.client import RequestWindow

    async def main() -> None:
        loop = asyncio.get_running_loop()
        window = RequestWindow(1)
        window.free -= 1  # the turn is taken
        second = asyncio.ensure_future(window.wait_turn(loop))
        third = asyncio.ensure_future(window.wait_turn(loop))
        await asyncio.sleep(0)
        window.release()  # to the second ...
        second.cancel()  # ... which is cancelled before it runs
        await asyncio.wait_for(third, 2.0)  # the third has the turn
        with pytest.raises(asyncio.CancelledError):
            await second
        assert window.free == 0 and not window.queue
        window.release()
        assert window.free == 1

    asyncio.run(main())
