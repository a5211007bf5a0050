"""The mux (`pyrtu.tcp.mux`: many Modbus TCP connections behind one descriptor;
C: csrc/rtu_mux_io.c, the twin: pyrtu/tcp/_pymux.py), on both backends, against
a scripted server on a real loopback socket: the request's bytes (built here with
`struct`, Messaging on TCP/IP Implementation Guide V1.0b 3.1.3), an answer whole
or in pieces, late answers dropped and counted, unit and function judged, the
timeout at its deadline, an invalid header, a connection closed while busy or
idle, and the calls it refuses."""

from __future__ import annotations

import errno
import math
import select
import socket
import struct
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

import pytest

from pyrtu.drivers.xfer import (
    STAGE_RECEIVE,
    STAGE_SEND,
    TCP_ANSWER,
    TCP_BAD_HEADER,
    TCP_CLOSED,
    TCP_ERRNO,
    TCP_EXCEPTION,
    TCP_MISMATCH,
    TCP_TIMEOUT,
)
from pyrtu.tcp.mux import REPEATING, RESENT, MuxDone, TcpMux
from pyrtu.tcp.mux_backends import available, open_mux

READ = bytes((3, 0, 0, 0, 2))  # FC 3, address 0, 2 registers
ANSWER = bytes((3, 4, 0x12, 0x34, 0x56, 0x78))


def adu(tid: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


@pytest.fixture
def mux(backend: ModuleType) -> Iterator[TcpMux]:
    if not available(backend.BACKEND):
        pytest.skip("no mux on this platform for this backend")  # (macOS C: the twin runs)
    m = open_mux(4, backend.BACKEND)
    yield m
    m.close()


@pytest.fixture
def pair(mux: TcpMux) -> Iterator[tuple[int, socket.socket]]:
    """A connection of the mux and the server's end of it."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen()
    client = socket.create_connection(srv.getsockname())
    peer, _ = srv.accept()
    srv.close()
    peer.settimeout(5)
    yield mux.attach(client), peer
    peer.close()


def records(mux: TcpMux, within: float = 5.0) -> list[MuxDone]:
    """Wait (select on the mux's descriptor, and its deadline) for records."""
    end = time.monotonic() + within
    if mux.service():  # (ended at once: no descriptor says so)
        return mux.take()
    while time.monotonic() < end:
        due = mux.deadline()
        wait = end - time.monotonic() if due is None else max(0.0, due - time.monotonic())
        select.select([mux.fd], [], [], min(wait, end - time.monotonic()))
        if mux.service():
            return mux.take()
    raise AssertionError("no record came")


@contextmanager
def served(mux: TcpMux, n: int) -> Iterator[tuple[list[int], list[socket.socket]]]:
    """``n`` connections of the mux to a loopback server, and the server's ends."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(n)
    conns: list[int] = []
    peers: list[socket.socket] = []
    try:
        for _ in range(n):
            conns.append(mux.attach(socket.create_connection(srv.getsockname())))
            peer = srv.accept()[0]
            peer.settimeout(5)
            peers.append(peer)
        yield conns, peers
    finally:
        srv.close()
        for peer in peers:
            peer.close()


@contextmanager
def stuffed(mux: TcpMux) -> Iterator[tuple[int, socket.socket, int]]:
    """A connection whose buffers are full (written to before it was attached, the
    server not reading): its number, the server's end, and the bytes written."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    client = socket.create_connection(srv.getsockname())
    peer, _ = srv.accept()
    srv.close()
    peer.settimeout(5)
    try:
        client.setblocking(False)
        junk = 0
        try:
            while True:
                junk += client.send(bytes(65536))
        except BlockingIOError:
            pass  # full: the kernel's buffers on both sides
        yield mux.attach(client), peer, junk
    finally:
        peer.close()


def test_an_answer_is_read_whole_and_handed_over(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 77, 0x1234, 5, READ, 2.0)
    assert peer.recv(260) == adu(0x1234, 5, READ)
    assert mux.service() == 0  # (nothing yet)
    peer.sendall(adu(0x1234, 5, ANSWER))
    (d,) = records(mux)
    assert (d.token, d.conn, d.status, d.tid, d.late, d.err, d.stage, d.flags) == (
        77, conn, TCP_ANSWER, 0x1234, 0, 0, 0, 0)  # fmt: skip
    assert d.adu == bytes((5,)) + ANSWER
    assert d.start <= d.end <= time.monotonic()
    assert mux.take() == [] and mux.deadline() is None
    # the next transaction on the same connection
    mux.submit(conn, 78, 0x1235, 5, READ, 2.0)
    assert peer.recv(260) == adu(0x1235, 5, READ)
    peer.sendall(adu(0x1235, 5, ANSWER))
    assert [(d.token, d.status) for d in records(mux)] == [(78, TCP_ANSWER)]


def test_late_answers_are_dropped_and_an_answer_in_pieces_is_awaited(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 9, 1, READ, 2.0)
    peer.recv(260)
    answer = adu(9, 1, ANSWER)
    peer.sendall(adu(7, 1, ANSWER) + adu(8, 1, ANSWER) + answer[:5])  # two late, a part
    time.sleep(0.05)
    assert mux.service() == 0
    peer.sendall(answer[5:])
    (d,) = records(mux)
    assert (d.status, d.tid, d.late, d.adu) == (TCP_ANSWER, 9, 2, bytes((1,)) + ANSWER)


def test_a_silent_server_times_out_at_the_deadline_and_its_late_answer_is_dropped(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 20, 1, READ, 0.2)
    due = mux.deadline()
    assert due is not None and 0.15 < due - time.monotonic() <= 0.2
    peer.recv(260)
    (d,) = records(mux)
    assert (d.status, d.adu, d.err, d.stage) == (TCP_TIMEOUT, b"", 0, 0)
    assert d.end - d.start >= 0.2  # not before its deadline
    peer.sendall(adu(20, 1, ANSWER))  # the answer, too late
    mux.submit(conn, 2, 21, 1, READ, 2.0)
    peer.recv(260)
    peer.sendall(adu(21, 1, ANSWER))
    (d,) = records(mux)
    assert (d.status, d.tid, d.late) == (TCP_ANSWER, 21, 1)


@pytest.mark.parametrize(
    ("unit", "pdu", "status"),
    [
        (1, bytes((0x83, 2)), TCP_EXCEPTION),  # [AP] 7: the function code + 0x80
        (2, ANSWER, TCP_MISMATCH),  # another unit
        (1, bytes((4, 4, 0, 0, 0, 0)), TCP_MISMATCH),  # another function
    ],
)
def test_the_unit_and_function_are_judged(
    mux: TcpMux, pair: tuple[int, socket.socket], unit: int, pdu: bytes, status: int
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 30, 1, READ, 2.0)
    peer.recv(260)
    peer.sendall(adu(30, unit, pdu))
    (d,) = records(mux)
    assert (d.status, d.adu) == (status, bytes((unit,)) + pdu)


def test_an_invalid_header_ends_the_connection(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 40, 1, READ, 2.0)
    peer.recv(260)
    peer.sendall(adu(40, 1, ANSWER, protocol=1))
    (d,) = records(mux)
    assert (d.status, d.err) == (TCP_BAD_HEADER, 1)  # MBAP_ERROR_BY_CODE[1]: protocol id
    assert d.broken
    mux.submit(conn, 2, 41, 1, READ, 2.0)  # nothing more on it: said at once
    assert [(d.status, d.err) for d in records(mux)] == [(TCP_BAD_HEADER, 1)]


def test_a_connection_closed_busy_or_idle_is_said(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 50, 1, READ, 2.0)
    peer.recv(260)
    peer.close()
    (d,) = records(mux)
    assert (d.status, d.stage, d.err) == (TCP_CLOSED, STAGE_RECEIVE, 0) and d.broken
    mux.submit(conn, 2, 51, 1, READ, 2.0)
    (d,) = records(mux, 1.0)
    assert d.status == TCP_CLOSED


def test_a_server_that_closes_while_idle_ends_the_next_transaction_at_once(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    peer.close()
    time.sleep(0.05)
    assert mux.service() == 0  # (idle: no record, the end kept)
    assert mux.submit(conn, 3, 60, 1, READ, 5.0)  # ended at once
    start = time.monotonic()
    (d,) = records(mux)
    assert (d.status, d.err, d.stage) == (TCP_CLOSED, 0, STAGE_RECEIVE)
    assert time.monotonic() - start < 1.0


def test_a_broadcast_ends_once_sent(mux: TcpMux, pair: tuple[int, socket.socket]) -> None:
    conn, peer = pair
    write = bytes((6, 0, 1, 0, 7))
    assert mux.submit(conn, 1, 70, 0, write, 2.0, awaited=False)
    (d,) = records(mux)
    assert (d.status, d.adu, d.err, d.stage, d.late) == (TCP_ANSWER, b"", 0, 0, 0)
    assert peer.recv(260) == adu(70, 0, write)


def test_what_the_mux_refuses(mux: TcpMux, pair: tuple[int, socket.socket]) -> None:
    conn, peer = pair
    # the smallest: transaction 0, unit 0, a PDU of one byte (FC 7 has no more)
    assert not mux.submit(conn, 0, 0, 0, bytes((7,)), 2.0)
    assert peer.recv(260) == adu(0, 0, bytes((7,)))
    peer.sendall(adu(0, 0, bytes((7, 0x55))))
    assert [(d.status, d.adu) for d in records(mux)] == [(TCP_ANSWER, bytes((0, 7, 0x55)))]
    for bad in [(conn, 1, 0x10000, 1, READ), (conn, 1, 1, 256, READ), (conn, 1, 1, 1, b""),
                (conn, 1, -1, 1, READ), (conn, 1, 1, -1, READ),
                (conn, 1, 1, 1, bytes(254)), (3, 1, 1, 1, READ), (conn, -1, 1, 1, READ),
                (conn, 2**64, 1, 1, READ), (-1, 1, 1, 1, READ),
                (2**32, 1, 1, 1, READ)]:  # fmt: skip
        with pytest.raises(ValueError, match="refused"):
            mux.submit(*bad, 1.0)
    with pytest.raises(ValueError, match="refused"):
        mux.submit(conn, 1, 1, 1, READ, float("nan"))
    mux.submit(conn, 1, 1, 1, READ, 2.0)
    with pytest.raises(ValueError, match="still in a transaction"):
        mux.submit(conn, 2, 2, 1, READ, 2.0)  # one in flight at a time
    peer.recv(260)
    peer.sendall(adu(1, 1, ANSWER))
    deadline = time.monotonic() + 5
    while not mux.service():  # ended, not taken yet: still refused
        assert time.monotonic() < deadline
        time.sleep(0.01)
    with pytest.raises(ValueError, match="still in a transaction"):
        mux.submit(conn, 2, 2, 1, READ, 2.0)
    mux.detach(conn)  # its record goes with it
    assert mux.take() == []
    socks = [socket.socket() for _ in range(4)]
    try:
        for s in socks:
            mux.attach(s)
        with pytest.raises(ValueError, match="all 4 connections"):
            mux.attach(socket.socket())
    finally:
        mux.close()


def test_many_connections_answer_in_one_service(backend: ModuleType) -> None:
    if not available(backend.BACKEND):
        pytest.skip("no mux on this platform for this backend")
    mux = open_mux(20, backend.BACKEND)
    try:
        with served(mux, 20) as (conns, peers):
            for i, conn in enumerate(conns):
                mux.submit(conn, 100 + i, i, 1, READ, 2.0)
            for i, p in enumerate(peers):
                assert p.recv(260) == adu(i, 1, READ)
                p.sendall(adu(i, 1, ANSWER))
            time.sleep(0.1)
            got = records(mux)
            while len(got) < 20:
                got += records(mux)
            assert sorted(d.token for d in got) == [100 + i for i in range(20)]
            assert {d.status for d in got} == {TCP_ANSWER}
    finally:
        mux.close()


@pytest.fixture
def stamping() -> Iterator[None]:
    """Linux turns receive time-stamping on for the whole system a moment after a
    first socket asks for it (deferred work), and off when the last one closes: a
    socket that asks, held open meanwhile, so that every answer here has its time."""
    keep = socket.socket()
    keep.setsockopt(socket.SOL_SOCKET, 35, 1)  # SO_TIMESTAMPNS (asm-generic)
    time.sleep(0.1)
    yield
    keep.close()


@pytest.mark.skipif(sys.platform != "linux", reason="SO_TIMESTAMPNS: Linux only")
def test_an_answers_time_is_when_it_came_not_when_it_was_read(
    mux: TcpMux, pair: tuple[int, socket.socket], stamping: None
) -> None:
    """The kernel's receive time (SO_TIMESTAMPNS): read 0.2 s after it came, the
    answer's end is when it came."""
    conn, peer = pair
    assert not mux.submit(conn, 1, 5, 1, READ, 5.0)
    peer.recv(260)
    peer.sendall(adu(5, 1, ANSWER))
    came = time.monotonic()
    time.sleep(0.2)
    read = time.monotonic()
    assert mux.service() == 1
    (d,) = mux.take()
    assert d.start <= d.end <= came + 0.05 < read, (d.end - came, read - came)


def test_the_requests_bounds(mux: TcpMux, pair: tuple[int, socket.socket]) -> None:
    """Transaction id 0..0xFFFF, unit 0..255, a PDU of 1..253 bytes, a timeout of 0
    or more ([TCP] 3.1.3: the length field counts the unit and the PDU, at most 254):
    the largest of each goes out as `struct` builds it."""
    conn, peer = pair
    pdu = bytes((16,)) + bytes(252)
    assert not mux.submit(conn, 2**63, 0xFFFF, 255, pdu, 0.0)
    assert peer.recv(300) == adu(0xFFFF, 255, pdu)
    (d,) = records(mux)
    assert (d.token, d.status) == (2**63, TCP_TIMEOUT)
    with pytest.raises(ValueError, match="refused"):
        mux.submit(conn, 1, 1, 1, READ, -0.001)
    # the largest token; a timeout past what a 64-bit count of nanoseconds holds
    assert not mux.submit(conn, 2**64 - 1, 1, 1, READ, 1e10)
    assert peer.recv(300) == adu(1, 1, READ)
    peer.sendall(adu(1, 1, ANSWER))
    (d,) = records(mux)
    assert (d.token, d.status, d.adu) == (2**64 - 1, TCP_ANSWER, bytes((1,)) + ANSWER)


def test_late_answers_while_idle_are_counted_in_the_next_transaction(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    """Answers that come while no transaction is in flight, a flood of them (more
    than the receive buffer's 520 bytes: it keeps only what is unresolved), are
    dropped as late and counted in the next record; its own answer is found."""
    conn, peer = pair
    late = b"".join(adu(i, 1, ANSWER) for i in range(0, 60))  # 60 x 13 bytes, tid 0 first
    peer.sendall(late)
    time.sleep(0.05)
    before = mux.services
    assert mux.service() == 0 and mux.service() == 0  # (two reads: the buffer filled)
    assert mux.services == before + 2
    assert not mux.submit(conn, 1, 70, 1, READ, 2.0)
    peer.recv(260)
    # one more late, its own, one late after it (counted in the next record)
    peer.sendall(adu(69, 1, ANSWER) + adu(70, 1, ANSWER) + adu(68, 1, ANSWER))
    (d,) = records(mux)
    assert (d.status, d.tid, d.late) == (TCP_ANSWER, 70, 61)
    assert not mux.submit(conn, 2, 71, 1, READ, 2.0)
    peer.recv(260)
    peer.sendall(adu(71, 1, ANSWER))
    (d,) = records(mux)
    assert (d.status, d.tid, d.late) == (TCP_ANSWER, 71, 1)


def test_an_invalid_header_while_idle_ends_the_next_transaction_at_once(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    peer.sendall(adu(1, 1, ANSWER) + adu(2, 1, ANSWER, protocol=7))
    time.sleep(0.05)
    assert mux.service() == 0
    assert mux.submit(conn, 1, 3, 1, READ, 2.0)  # ended at once: nothing sent
    (d,) = mux.take() if mux.service() else []
    assert (d.status, d.err, d.late, d.stage) == (TCP_BAD_HEADER, 1, 1, STAGE_RECEIVE)


def test_the_stage_and_error_of_an_end_are_said(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 8, 1, READ, 2.0)
    peer.recv(260)
    peer.sendall(adu(8, 1, ANSWER, protocol=1))
    (d,) = records(mux)
    assert (d.status, d.err, d.stage) == (TCP_BAD_HEADER, 1, 0)


def test_deadlines_follow_the_transactions_in_flight(mux: TcpMux) -> None:
    """The first deadline is the earliest transaction's still in flight: not one
    answered, not one of a connection detached (nor of an earlier connection in
    its place), none once nothing is in flight."""
    with served(mux, 2) as (conns, peers):
        assert mux.deadline() is None
        t0 = time.monotonic()
        mux.submit(conns[0], 1, 1, 1, READ, 1.0)
        mux.submit(conns[1], 2, 2, 1, READ, 3.0)
        due = mux.deadline()
        assert due is not None and t0 + 1.0 <= due < t0 + 1.5
        peers[0].recv(260)
        peers[0].sendall(adu(1, 1, ANSWER))
        (d,) = records(mux)
        assert d.token == 1
        due = mux.deadline()
        assert due is not None and t0 + 3.0 <= due < t0 + 3.5
        mux.submit(conns[0], 4, 4, 1, READ, 4.0)  # its next: the later deadline, not its old
        due = mux.deadline()
        assert due is not None and t0 + 3.0 <= due < t0 + 3.5
        peers[0].recv(260)
        peers[0].sendall(adu(4, 1, ANSWER))
        (d,) = records(mux)
        assert d.token == 4
        mux.detach(conns[1])  # its transaction forgotten, and its deadline
        assert mux.deadline() is None
        with served(mux, 1) as (again, _):
            assert again == [conns[1]]  # (the same number: an earlier one's entry is stale)
            mux.submit(again[0], 3, 3, 1, READ, 5.0)
            due = mux.deadline()
            assert due is not None and due >= t0 + 5.0


def test_attached_sockets_are_non_blocking_and_closed_with_the_mux(backend: ModuleType) -> None:
    if not available(backend.BACKEND):
        pytest.skip("no mux on this platform for this backend")
    mux = open_mux(2, backend.BACKEND)
    assert mux.services == 0
    a, b = socket.socketpair()
    try:
        mux.attach(a)
        assert a.getblocking() is False
        mux.close()
        assert a.fileno() == -1  # closed by the mux
        mux.close()  # (twice: nothing more)
    finally:
        b.close()


def test_a_connection_reset_while_idle_ends_the_next_transaction_with_its_error(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    peer.close()  # a reset, not an end of file
    time.sleep(0.05)
    assert mux.service() == 0  # (idle: no record, the error kept)
    assert mux.submit(conn, 4, 80, 1, READ, 2.0)
    (d,) = mux.take() if mux.service() else []
    assert (d.status, d.err, d.stage) == (TCP_ERRNO, errno.ECONNRESET, STAGE_RECEIVE)
    assert d.broken


def test_a_request_the_socket_has_no_room_for_goes_out_when_it_has(mux: TcpMux) -> None:
    """The connection's send buffer full (filled before it was attached, the server
    not reading): the request waits for room (epoll's ``EPOLLOUT``), goes out whole
    when the server reads, and its answer is taken."""
    with stuffed(mux) as (conn, peer, junk):
        assert not mux.submit(conn, 1, 9, 1, READ, 10.0)
        assert mux.service() == 0  # (no room yet: nothing sent, nothing ended)
        request = adu(9, 1, READ)
        got = b""
        while len(got) < junk + len(request):
            got += peer.recv(1 << 20)
            mux.service()  # (room now and then: the rest goes out)
        assert got[junk:] == request
        peer.sendall(adu(9, 1, ANSWER))
        (d,) = records(mux)
        assert (d.status, d.tid) == (TCP_ANSWER, 9)


def test_of_two_in_flight_the_one_due_first_times_out_first(mux: TcpMux) -> None:
    with served(mux, 2) as (conns, _):
        mux.submit(conns[1], 2, 2, 1, READ, 5.0)
        mux.submit(conns[0], 1, 1, 1, READ, 0.1)
        time.sleep(0.2)
        assert mux.service() == 1
        assert [(d.token, d.status) for d in mux.take()] == [(1, TCP_TIMEOUT)]
        due = mux.deadline()
        assert due is not None and due > time.monotonic() + 4


def test_a_request_that_never_went_out_is_dropped_at_its_timeout(mux: TcpMux) -> None:
    """No room for the request until its timeout: nothing of it went out, so the
    connection goes on (the next transaction's request is the one that goes), and
    the old one is never sent."""
    with stuffed(mux) as (conn, peer, junk):
        assert not mux.submit(conn, 1, 9, 1, READ, 0.1)
        (d,) = records(mux)
        assert d.status == TCP_TIMEOUT and not d.broken
        got = b""
        while len(got) < junk:
            got += peer.recv(1 << 20)
        time.sleep(0.05)
        # room now, and nothing to send: the descriptor is quiet (no wake-up loop)
        assert select.select([mux.fd], [], [], 0.05)[0] == []
        assert not mux.submit(conn, 2, 10, 1, READ, 5.0)
        while len(got) < junk + 12:
            got += peer.recv(1 << 20)
            mux.service()
        assert got[junk:] == adu(10, 1, READ)  # the new request, not the dropped one
        peer.sendall(adu(10, 1, ANSWER))
        assert [(d.status, d.tid) for d in records(mux)] == [(TCP_ANSWER, 10)]


def test_an_answered_transactions_deadline_ends_no_later_one(mux: TcpMux) -> None:
    """A transaction answered before its deadline leaves nothing due then: not the
    connection's next transaction (a longer one), and not another connection's
    due after it (which times out at its own deadline)."""
    with served(mux, 2) as (conns, peers):
        mux.submit(conns[0], 1, 1, 1, READ, 0.1)
        peers[0].recv(260)
        peers[0].sendall(adu(1, 1, ANSWER))
        assert [d.token for d in records(mux)] == [1]
        mux.submit(conns[0], 2, 2, 1, READ, 5.0)  # the same connection, a longer wait
        mux.submit(conns[1], 3, 3, 1, READ, 0.15)
        time.sleep(0.3)  # past the answered one's deadline and the other's
        assert mux.service() == 1
        assert [(d.token, d.status) for d in mux.take()] == [(3, TCP_TIMEOUT)]


def test_a_send_that_fails_ends_the_transaction_with_its_error(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    """The server reset the connection and the mux has not read it yet: the send
    fails, and the record says so (its errno, at the send); nothing waits, and a
    service with nothing ready returns at once."""
    conn, peer = pair
    peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    peer.close()
    time.sleep(0.05)  # (the reset has come; no service has read it)
    assert mux.submit(conn, 5, 90, 1, READ, 2.0)  # ended at once
    (d,) = mux.take() if mux.service() else []
    assert (d.status, d.stage, d.err) == (TCP_ERRNO, STAGE_SEND, errno.ECONNRESET)
    t0 = time.monotonic()
    assert mux.service() == 0
    assert time.monotonic() - t0 < 0.5  # (a look, not a wait)


# ------------------------------------------------------------------ the repeat


def nothing_sent(peer: socket.socket) -> bool:
    """Whether the server's end has nothing to read."""
    return not select.select([peer], [], [], 0)[0]


def answered_once(mux: TcpMux, peer: socket.socket, tid: int, pdu: bytes = ANSWER) -> MuxDone:
    """The request ``tid`` (read by the server), its answer ``pdu``, its record."""
    assert peer.recv(260) == adu(tid, 5, READ)
    peer.sendall(adu(tid, 5, pdu))
    (d,) = records(mux)
    return d


def wait_until(t: float) -> None:
    time.sleep(max(0.0, t - time.monotonic()))


def test_a_repeat_sends_the_request_again_with_the_next_transaction_id(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 77, 0xFFFE, 5, READ, 2.0)
    mux.repeat(conn, time.monotonic(), 0.05)
    d = answered_once(mux, peer, 0xFFFE)  # the submit's
    assert (d.token, d.status, d.flags) == (77, TCP_ANSWER, REPEATING)
    mux.service()  # (due: sent; the next transaction id)
    d = answered_once(mux, peer, 0xFFFF)
    assert (d.token, d.tid, d.flags) == (77, 0xFFFF, REPEATING | RESENT)
    assert d.adu == bytes((5,)) + ANSWER
    changed = bytes((3, 4, 0, 1, 0, 2))
    wait_until(d.start + 0.05)
    mux.service()
    d = answered_once(mux, peer, 0, changed)  # (the id wraps to 0)
    assert (d.tid, d.flags, d.adu) == (0, REPEATING | RESENT, bytes((5,)) + changed)


@pytest.mark.wall_clock
def test_a_repeat_is_sent_when_due_and_keeps_its_beat(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    """(Not sent before it is due: the service runs well within the 0.2 s before.)"""
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    answered_once(mux, peer, 10)
    first = time.monotonic() + 0.2
    mux.repeat(conn, first, 0.3)
    assert mux.deadline() == pytest.approx(first, abs=1e-6)  # an idle connection's due
    mux.service()
    assert nothing_sent(peer)  # not before it is due
    wait_until(first)
    mux.service()
    d = answered_once(mux, peer, 11)
    assert d.start >= first - 1e-6 and d.flags == REPEATING | RESENT
    # the next is due one interval after the time this one was due, not after its send
    assert mux.deadline() == pytest.approx(first + 0.3, abs=1e-6)


def test_a_repeat_more_than_an_interval_behind_is_sent_at_once_and_its_beat_starts_again(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    answered_once(mux, peer, 10)
    mux.repeat(conn, time.monotonic() - 1.0, 0.3)  # three intervals behind
    mux.service()
    d = answered_once(mux, peer, 11)
    assert mux.deadline() == pytest.approx(d.start, abs=1e-6)  # due again at once
    mux.service()
    answered_once(mux, peer, 12)
    # less than an interval behind: the beat goes on from when it was due
    behind = time.monotonic() - 0.2
    mux.repeat(conn, behind, 0.3)
    mux.service()
    answered_once(mux, peer, 13)
    assert mux.deadline() == pytest.approx(behind + 0.3, abs=1e-6)


@pytest.mark.parametrize("end", ["exception", "timeout", "late", "closed"])
def test_a_repeat_ends_with_a_transaction_that_is_not_a_plain_answer(
    mux: TcpMux, pair: tuple[int, socket.socket], end: str
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 0.3 if end == "timeout" else 5.0)
    mux.repeat(conn, time.monotonic(), 0.05)
    answered_once(mux, peer, 10)
    mux.service()
    assert peer.recv(260) == adu(11, 5, READ)
    if end == "exception":
        peer.sendall(adu(11, 5, bytes((0x83, 2))))
    elif end == "late":
        peer.sendall(adu(10, 5, ANSWER) + adu(11, 5, ANSWER))
    elif end == "closed":
        peer.shutdown(socket.SHUT_WR)
    (d,) = records(mux)
    status = {"exception": TCP_EXCEPTION, "timeout": TCP_TIMEOUT, "late": TCP_ANSWER,
              "closed": TCP_CLOSED}[end]  # fmt: skip
    assert (d.status, d.flags) == (status, RESENT)  # not REPEATING: it ended
    time.sleep(0.1)
    mux.service()
    assert nothing_sent(peer) and mux.take() == [] and mux.deadline() is None


def test_unrepeat_says_whether_a_record_is_still_to_come(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    mux.repeat(conn, time.monotonic() + 0.05, 0.05)
    assert mux.unrepeat(conn) is True  # in flight
    d = answered_once(mux, peer, 10)
    assert d.flags == 0
    time.sleep(0.1)
    mux.service()
    assert nothing_sent(peer) and mux.deadline() is None
    mux.repeat(conn, time.monotonic(), 0.05)
    mux.service()
    peer.recv(260)
    peer.sendall(adu(11, 5, ANSWER))
    while not mux.service():  # its record waits, not taken
        select.select([mux.fd], [], [], 1.0)
    assert mux.unrepeat(conn) is True  # (its record still comes)
    (d,) = mux.take()
    assert d.flags == RESENT
    assert mux.unrepeat(conn) is False  # idle: nothing comes
    assert mux.take() == []


def test_a_repeat_waits_for_the_record_before_it_to_be_taken(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    mux.repeat(conn, time.monotonic(), 0.01)
    assert peer.recv(260) == adu(10, 5, READ)
    peer.sendall(adu(10, 5, ANSWER))
    while not mux.service():
        select.select([mux.fd], [], [], 1.0)
    time.sleep(0.03)
    assert mux.service() == 1
    assert nothing_sent(peer)  # due, but its record before is not taken
    due = mux.deadline()  # (due now: collect at once)
    assert due is not None and due <= time.monotonic()
    assert len(mux.take()) == 1
    mux.service()
    assert peer.recv(260) == adu(11, 5, READ)


def test_a_busy_connections_due_repeat_waits_for_its_answer_or_timeout(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 60.0)
    mux.repeat(conn, time.monotonic() - 0.1, 0.05)  # due, but the submit is in flight
    due = mux.deadline()
    assert due is not None and due > time.monotonic() + 30  # the timeout's, not the past due
    mux.service()
    assert peer.recv(260) == adu(10, 5, READ)
    assert nothing_sent(peer)  # not sent again while the one before is in flight


def test_a_submit_or_a_detach_ends_the_repeat(mux: TcpMux, pair: tuple[int, socket.socket]) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    answered_once(mux, peer, 10)
    mux.repeat(conn, time.monotonic() + 0.05, 0.05)
    mux.submit(conn, 2, 20, 5, READ, 2.0)  # a request of its own
    d = answered_once(mux, peer, 20)
    assert d.flags == 0 and mux.deadline() is None
    mux.repeat(conn, time.monotonic() + 0.05, 0.05)
    mux.detach(conn)
    assert mux.deadline() is None
    with pytest.raises(ValueError, match="not attached"):
        mux.unrepeat(conn)


@pytest.mark.parametrize(
    ("first", "interval"),
    [(0.0, 0.0), (0.0, -1.0), (0.0, float("nan")), (float("nan"), 1.0), (0.0, 1.2e9),
     (0.0, 1e-10), (0.0, 0.9999999995e-9), (float("inf"), 1.0), (-9e9, 1.0), (9e9, 1.0)],
)  # fmt: skip
def test_a_repeat_with_a_bad_time_is_refused(
    mux: TcpMux, pair: tuple[int, socket.socket], first: float, interval: float
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    with pytest.raises(ValueError, match="refused to repeat"):
        mux.repeat(conn, first, interval)
    answered_once(mux, peer, 10)
    assert mux.deadline() is None  # nothing changed


def test_a_repeat_needs_an_attached_connection_with_an_awaited_request(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    with pytest.raises(ValueError, match="refused to repeat"):
        mux.repeat(conn, 0.0, 1.0)  # no request yet
    with pytest.raises(ValueError, match="refused to repeat"):
        mux.repeat(3, 0.0, 1.0)  # not attached
    with pytest.raises(ValueError, match="not attached"):
        mux.unrepeat(3)
    mux.submit(conn, 1, 10, 0, READ, 2.0, awaited=False)  # a broadcast
    assert [d.status for d in records(mux)] == [TCP_ANSWER]
    assert peer.recv(260) == adu(10, 0, READ)
    with pytest.raises(ValueError, match="refused to repeat"):
        mux.repeat(conn, 0.0, 1.0)
    mux.submit(conn, 2, 11, 5, READ, 2.0)
    mux.repeat(conn, 0.0, 1e-9)  # the shortest interval: one nanosecond
    answered_once(mux, peer, 11)


def test_a_repeat_is_refused_while_a_record_waits(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    assert peer.recv(260) == adu(10, 5, READ)
    peer.sendall(adu(10, 5, ANSWER))
    while not mux.service():
        select.select([mux.fd], [], [], 1.0)
    with pytest.raises(ValueError, match="refused to repeat"):
        mux.repeat(conn, 0.0, 1.0)  # (that record was judged without it)
    (d,) = mux.take()
    assert d.flags == 0
    mux.repeat(conn, 0.0, 1.0)


def test_a_repeat_at_the_bounds_of_its_times_is_taken(
    mux: TcpMux, pair: tuple[int, socket.socket]
) -> None:
    """The first time just inside (-9e9, 9e9) s, the interval from 1 ns to 1e9 s
    (2**60 ns is the C mux's most: 1.15e9 s)."""
    conn, peer = pair
    mux.submit(conn, 1, 10, 5, READ, 2.0)
    for first in (math.nextafter(-9e9, 0), math.nextafter(9e9, 0)):
        for interval in (1e-9, 1e9):
            mux.repeat(conn, first, interval)
    answered_once(mux, peer, 10)


def test_deadline_is_the_first_of_the_timeouts_and_the_idle_repeats(mux: TcpMux) -> None:
    with served(mux, 3) as (conns, peers):
        for conn, peer in zip(conns[:2], peers[:2], strict=True):
            mux.submit(conn, 1, 10, 5, READ, 2.0)
            answered_once(mux, peer, 10)
        now = time.monotonic()
        mux.repeat(conns[0], now + 50, 1.0)
        mux.repeat(conns[1], now + 30, 1.0)
        assert mux.deadline() == pytest.approx(now + 30, abs=1e-6)
        mux.submit(conns[2], 1, 10, 5, READ, 10.0)  # in flight: its timeout is sooner
        due = mux.deadline()
        assert due is not None and due < now + 30


class _Clock:
    """`time` as the twin sees it: a clock the test sets."""

    def __init__(self, now: float) -> None:
        self.now = now

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return self.now


@pytest.mark.parametrize(("late", "next_due"), [(2.0, 11.0), (2.5, 12.5)])
def test_the_twins_repeat_exactly_two_intervals_behind_keeps_its_beat(
    monkeypatch: pytest.MonkeyPatch, late: float, next_due: float
) -> None:
    """The boundary of the beat, on the twin (whose clock a test can set; C reads
    CLOCK_MONOTONIC): due at 10 every second and sent at 12, the next is due at
    11, one interval on (11 + 1 is not before 12), as
    tests/poller/test_poller_schedule_edges.py has the scheduler do; sent at
    12.5, more than an interval behind, the beat starts again from the send."""
    from pyrtu.tcp import _pymux

    clock = _Clock(5.0)
    monkeypatch.setattr(_pymux, "time", clock)
    mux = _pymux.PyMux(1)
    try:
        with served(mux, 1) as ((conn,), (peer,)):
            mux.submit(conn, 1, 10, 5, READ, 2.0)
            answered_once(mux, peer, 10)
            mux.repeat(conn, 10.0, 1.0)
            clock.now = 10.0 + late
            mux.service()
            answered_once(mux, peer, 11)
            assert mux.deadline() == next_due
    finally:
        mux.close()
