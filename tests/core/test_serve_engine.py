"""The server engine (csrc/rtu_serve_io.c) through cffi, on real sockets: plain reads
answered by its thread from an image (csrc/rtu_image.c), every other request handed to
the caller as an event and answered with rtu_serve_send, in request order.

Messaging on TCP/IP Implementation Guide V1.0b 3.1.3: the answer carries the request's
transaction id and unit id, protocol id 0, length 1 + PDU.  Waits are bounded (select on
the engine's eventfd or the client's socket with a timeout); a condition the engine
signals nothing for (a partial request seen) is polled until a deadline.
"""

from __future__ import annotations

import errno
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest
from c_core import needs_c

import pyrtu
from pyrtu.core._pure.image import HELD, PLAIN, image_answer
from pyrtu.core._pure.mbap import ERR_LENGTH, ERR_PROTOCOL

HAVE_C = "c" in pyrtu.available_backends()
pytestmark = needs_c(not HAVE_C)

PATIENCE = 5.0  # seconds: how long a failure takes, not a measurement
SILENCE = 0.3  # seconds a test waits to see that nothing comes

REQUEST, CLOSED, BAD_HEADER, STALLED = 1, 2, 3, 4


def _core() -> tuple[Any, Any]:
    from pyrtu.core._rtu_core import ffi, lib

    if lib.rtu_serve_size(1) == 0:
        pytest.skip("the server engine is Linux's (epoll)")
    return ffi, lib


def adu(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def read_pdu(fc: int, address: int, quantity: int) -> bytes:
    return struct.pack(">BHH", fc, address, quantity)


class Image:
    """An rtu_image over cffi memory: ``tables[t]`` is a list of (start, flags, values);
    ``values(t, i)`` the cffi array of range i of table t (to change under the lock)."""

    def __init__(self, tables: Sequence[Sequence[tuple[int, int, Sequence[int]]]]) -> None:
        ffi, _ = _core()
        self.img = ffi.new("rtu_image *")
        self.tables = [[(s, f, list(v)) for s, f, v in t] for t in tables]
        self.arrays: list[list[Any]] = []
        self.keep: list[Any] = []
        for t, ranges in enumerate(tables):
            arrays: list[Any] = []
            if ranges:
                arr = ffi.new("rtu_image_range[]", len(ranges))
                for i, (start, flags, values) in enumerate(ranges):
                    vals = ffi.new("uint16_t[]", list(values))
                    arrays.append(vals)
                    arr[i].start, arr[i].count, arr[i].flags = start, len(values), flags
                    arr[i].values = vals
                self.keep.append(arr)
                self.img.ranges[t] = arr
                self.img.nranges[t] = len(ranges)
            self.arrays.append(arrays)

    def answer(self, unit: int, request: bytes) -> bytes | None:
        """The ADU the engine must send for ``request`` (the twin's answer)."""
        pdu = image_answer(self.tables, request[7:])
        return None if pdu is None else adu(struct.unpack(">H", request[:2])[0], unit, pdu)


HOLDING = [(i * 257) & 0xFFFF for i in range(200)]


def holding_image() -> Image:
    """Holding registers 0..199, coils 0..99, a held input register range at 10."""
    return Image(
        [
            [(0, PLAIN, [i % 3 == 0 for i in range(100)])],
            [],
            [(0, PLAIN, HOLDING)],
            [(0, PLAIN, [1, 2]), (10, HELD, [7])],
        ]
    )


class Engine:
    """One rtu_serve, destroyed at the end of the test."""

    def __init__(self, capacity: int = 4, max_unsent: int = 1 << 20) -> None:
        ffi, lib = _core()
        self.ffi, self.lib = ffi, lib
        size = lib.rtu_serve_size(capacity)
        assert size > 0
        self.mem = ffi.new("uint64_t[]", (size + 7) // 8)
        self.s = ffi.cast("rtu_serve *", self.mem)
        assert lib.rtu_serve_init(self.s, capacity, max_unsent) == lib.RTU_OK
        self.out = ffi.new("rtu_serve_event[]", 16)
        self.images: list[Image] = []
        #: the routes every connection attached here carries (set before attaching)
        self.routes = ffi.new("const rtu_image *[256]")

    def route(self, unit: int, image: Image | None) -> None:
        """Unit ``unit`` to ``image`` for the connections attached from now on."""
        if image is not None:
            self.images.append(image)  # alive as long as the engine
        self.routes[unit] = self.ffi.NULL if image is None else image.img

    def attach(self, conn: int, sndbuf: int = 0, defer: int = 0) -> socket.socket:
        """A socket pair, its server end attached as ``conn``: the client end."""
        client, server = socket.socketpair()
        if sndbuf:
            server.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, sndbuf)
        fd = server.detach()
        assert self.lib.rtu_serve_attach(self.s, conn, fd, self.routes, defer) == self.lib.RTU_OK
        client.settimeout(PATIENCE)
        return client

    def take(self, timeout: float = PATIENCE) -> list[tuple[int, int, int, bytes, int]]:
        """The events waiting, after at most ``timeout`` for the first: (conn, kind,
        err, adu, at)."""
        fd = self.lib.rtu_serve_fd(self.s)
        select.select([fd], [], [], timeout)
        n = self.lib.rtu_serve_take(self.s, self.out, 16)
        return [
            (
                e.conn,
                e.kind,
                e.err,
                bytes(self.ffi.buffer(e.adu, e.len)),
                e.at,
            )
            for e in (self.out[i] for i in range(n))
        ]

    def waiting(self) -> bool:
        """Whether the eventfd is readable now."""
        fd = self.lib.rtu_serve_fd(self.s)
        return bool(select.select([fd], [], [], 0)[0])

    def send(self, conn: int, data: bytes) -> int:
        return int(self.lib.rtu_serve_send(self.s, conn, data, len(data)))

    def state(self, conn: int) -> Any:
        st = self.ffi.new("rtu_serve_conn_state *")
        assert self.lib.rtu_serve_conn(self.s, conn, st) == self.lib.RTU_OK
        return st

    def stats(self) -> tuple[int, int, int, list[int]]:
        st = self.ffi.new("rtu_serve_stats *")
        assert self.lib.rtu_serve_stats_get(self.s, st) == self.lib.RTU_OK
        return st.requests, st.answered, st.handed, list(st.by_function)

    def until(self, condition: Callable[[], bool], what: str) -> None:
        give_up = time.monotonic() + PATIENCE
        while not condition():
            assert time.monotonic() < give_up, f"gave up waiting for {what}"
            time.sleep(0.002)

    def destroy(self) -> None:
        self.lib.rtu_serve_destroy(self.s)


@pytest.fixture
def engine() -> Iterator[Engine]:
    e = Engine()
    yield e
    e.destroy()


def recv_exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        assert chunk, f"end of file after {len(data)} of {n} bytes"
        data += chunk
    return data


def recv_adu(sock: socket.socket) -> bytes:
    head = recv_exactly(sock, 7)
    return head + recv_exactly(sock, struct.unpack(">H", head[4:6])[0] - 1)


def silent(sock: socket.socket, seconds: float = SILENCE) -> bool:
    return not select.select([sock], [], [], seconds)[0]


# ------------------------------------------------------------------ plain reads


def test_plain_reads_answered_without_an_event(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    before = time.monotonic_ns()
    client = engine.attach(0)
    for tid, pdu in enumerate(
        [read_pdu(3, 0, 1), read_pdu(3, 75, 125), read_pdu(1, 3, 19), read_pdu(4, 0, 2)]
    ):
        request = adu(0x1200 + tid, 1, pdu)
        client.sendall(request)
        answer = recv_adu(client)
        assert answer == image.answer(1, request)
        assert answer[:2] == request[:2] and answer[2:4] == b"\0\0" and answer[6] == 1
    assert engine.take(0) == [] and not engine.waiting()
    assert engine.stats() == (4, 4, 0, [0, 1, 0, 2, 1])
    st = engine.state(0)
    assert st.answered == 4 and st.unsent == 0 and st.handed == 0 and st.partial_since == 0
    assert before <= st.connected <= st.last_request <= time.monotonic_ns()


def test_an_answer_is_the_exact_bytes(engine: Engine) -> None:
    engine.route(1, holding_image())
    client = engine.attach(0)
    client.sendall(adu(0xBEEF, 1, read_pdu(3, 1, 2)))
    assert recv_adu(client) == bytes.fromhex("beef 0000 0007 01 03 04 0101 0202")
    client.sendall(adu(7, 1, read_pdu(1, 0, 10)))  # coils 0, 3, 6, 9: 0x49, 0x02
    assert recv_adu(client) == bytes.fromhex("0007 0000 0005 01 01 02 49 02")


def test_two_and_three_requests_in_one_segment_in_order(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    engine.route(0xFF, image)
    client = engine.attach(1)
    for count in (2, 3):
        requests = [
            adu(100 * count + i, (1, 0xFF)[i % 2], read_pdu(3, i, 1 + i)) for i in range(count)
        ]
        client.sendall(b"".join(requests))
        for r in requests:
            assert recv_adu(client) == image.answer(r[6], r)
    assert engine.take(0) == []
    assert engine.stats()[:3] == (5, 5, 0)


def test_a_request_split_across_two_sends(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    request = adu(9, 1, read_pdu(3, 5, 3))
    before = time.monotonic_ns()
    client.sendall(request[:5])
    engine.until(lambda: engine.state(0).partial_since != 0, "the partial request seen")
    st = engine.state(0)
    assert before <= st.partial_since <= time.monotonic_ns() and st.last_request == 0
    assert silent(client, 0.05)
    client.sendall(request[5:])
    assert recv_adu(client) == image.answer(1, request)
    st = engine.state(0)
    assert st.partial_since == 0 and st.last_request >= before and st.answered == 1


def test_the_partial_request_after_a_whole_one(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    first, second = adu(1, 1, read_pdu(3, 0, 1)), adu(2, 1, read_pdu(3, 1, 1))
    client.sendall(first + second[:9])
    assert recv_adu(client) == image.answer(1, first)
    engine.until(lambda: engine.state(0).partial_since != 0, "the partial request seen")
    client.sendall(second[9:])
    assert recv_adu(client) == image.answer(1, second)
    assert engine.state(0).partial_since == 0


# ------------------------------------------------------------ handed to Python


def test_a_write_is_handed_over_and_the_read_after_it_waits(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(2)
    write = adu(0x0101, 1, bytes.fromhex("06 0004 1234"))
    read = adu(0x0102, 1, read_pdu(3, 0, 2))
    before = time.monotonic_ns()
    client.sendall(write)
    events = engine.take()
    assert [(c, k, e, a) for c, k, e, a, _ in events] == [(2, REQUEST, 0, write)]
    assert before <= events[0][4] <= time.monotonic_ns()
    assert engine.state(2).handed == 1
    client.sendall(read)
    assert silent(client)  # not answered: the write's answer comes first
    assert engine.take(0) == [] and engine.stats() == (1, 0, 1, [0] * 5)
    assert engine.send(2, write) == engine.lib.RTU_OK  # FC 06's answer echoes it
    assert recv_adu(client) == write
    assert recv_adu(client) == image.answer(1, read)
    assert engine.state(2).handed == 0
    assert engine.stats() == (2, 1, 1, [0, 0, 0, 1, 0])


def test_requests_after_a_handed_one_in_the_same_segment(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    reads = [adu(10 + i, 1, read_pdu(3, i, 1)) for i in range(3)]
    write = adu(20, 1, bytes.fromhex("10 0000 0001 02 0000"))
    client.sendall(reads[0] + write + reads[1] + reads[2])
    assert recv_adu(client) == image.answer(1, reads[0])
    [(conn, kind, _, got, _)] = engine.take()
    assert (conn, kind, got) == (0, REQUEST, write)
    assert silent(client)
    answer = adu(20, 1, bytes.fromhex("10 0000 0001"))
    assert engine.send(0, answer) == engine.lib.RTU_OK
    assert [recv_adu(client) for _ in range(3)] == [
        answer,
        *(image.answer(1, r) for r in reads[1:]),
    ]
    assert engine.stats()[:3] == (4, 3, 1)


def test_an_empty_answer_sends_nothing_and_resumes(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    broadcastish = adu(1, 1, bytes.fromhex("08 0004 0000"))  # listen-only: no answer
    read = adu(2, 1, read_pdu(3, 0, 1))
    client.sendall(broadcastish + read)
    assert [k for _, k, *_ in engine.take()] == [REQUEST]
    assert engine.send(0, b"") == engine.lib.RTU_OK
    assert recv_adu(client) == image.answer(1, read)


def test_a_unit_without_an_image_and_exceptions_are_handed_over(engine: Engine) -> None:
    engine.route(1, holding_image())
    client = engine.attach(0)
    cases = [
        adu(1, 2, read_pdu(3, 0, 1)),  # unit 2: no image
        adu(2, 1, read_pdu(3, 199, 2)),  # 200 lies outside every range
        adu(3, 1, read_pdu(4, 10, 1)),  # a held range
        adu(4, 1, read_pdu(3, 0, 126)),  # quantity past 125
        adu(5, 1, read_pdu(3, 0, 1) + b"\0"),  # a PDU of 6 bytes
    ]
    for request in cases:
        client.sendall(request)
        [(_, kind, _, got, _)] = engine.take()
        assert (kind, got) == (REQUEST, request)
        exception = adu(request[0] << 8 | request[1], request[6], bytes((request[7] | 0x80, 2)))
        assert engine.send(0, exception) == engine.lib.RTU_OK
        assert recv_adu(client) == exception
    assert engine.stats() == (5, 0, 5, [0] * 5)
    assert engine.lib.rtu_serve_defer(engine.s, 0, 1) == engine.lib.RTU_OK  # Python's again
    client.sendall(adu(9, 1, read_pdu(3, 0, 1)))
    assert [k for _, k, *_ in engine.take()] == [REQUEST]


def test_defer(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0, defer=1)  # deferring from the start
    other = engine.attach(1)  # its neighbour is not
    read = adu(1, 1, read_pdu(3, 0, 1))
    other.sendall(read)
    assert recv_adu(other) == image.answer(1, read)
    client.sendall(read)
    [(conn, kind, _, got, _)] = engine.take()
    assert (conn, kind, got) == (0, REQUEST, read)
    assert engine.lib.rtu_serve_defer(engine.s, 0, 0) == engine.lib.RTU_OK
    assert engine.lib.rtu_serve_defer(engine.s, 2, 0) == engine.lib.RTU_EINVAL  # not attached
    client.sendall(read)  # (behind the handed one)
    assert silent(client, 0.05)
    assert engine.send(0, b"x" * 7 + b"\x03") == engine.lib.RTU_OK  # Python's own answer
    assert recv_exactly(client, 8) == b"x" * 7 + b"\x03"
    assert recv_adu(client) == image.answer(1, read)


def test_send_refuses_what_was_not_handed(engine: Engine) -> None:
    lib = engine.lib
    client = engine.attach(0)
    assert engine.send(0, b"abc") == lib.RTU_EINVAL  # nothing handed
    assert engine.send(1, b"abc") == lib.RTU_EINVAL  # not attached
    assert engine.send(99, b"abc") == lib.RTU_EINVAL  # past the capacity
    request = adu(1, 1, read_pdu(3, 0, 1))  # unit 1: no image
    client.sendall(request)
    assert select.select([lib.rtu_serve_fd(engine.s)], [], [], PATIENCE)[0]
    engine.until(lambda: engine.state(0).handed == 1, "the request handed")
    assert engine.send(0, b"abc") == lib.RTU_EINVAL  # handed but not taken yet
    assert [k for _, k, *_ in engine.take()] == [REQUEST]
    assert engine.send(0, b"\0" * 261) == lib.RTU_EINVAL  # longer than an ADU
    assert engine.send(0, b"\0" * 260) == lib.RTU_OK
    assert engine.send(0, b"abc") == lib.RTU_EINVAL  # answered already
    assert recv_exactly(client, 260) == b"\0" * 260


# ------------------------------------------------------------ ends of a connection


def test_a_bad_header_ends_reading(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    good = adu(1, 1, read_pdu(3, 0, 1))
    bad = struct.pack(">HHHB", 2, 1, 6, 1) + read_pdu(3, 0, 1)  # protocol id 1
    client.sendall(good + bad + good)
    assert recv_adu(client) == image.answer(1, good)
    [(conn, kind, err, _, _)] = engine.take()
    assert (conn, kind, err) == (0, BAD_HEADER, ERR_PROTOCOL)
    client.sendall(good)
    assert silent(client) and engine.take(0) == []
    client2 = engine.attach(1)
    client2.sendall(struct.pack(">HHHB", 2, 0, 255, 1))  # length past 254
    [(conn, kind, err, _, _)] = engine.take()
    assert (conn, kind, err) == (1, BAD_HEADER, ERR_LENGTH)


def test_the_client_closes(engine: Engine) -> None:
    client = engine.attach(3)
    client.close()
    [(conn, kind, err, _, _)] = engine.take()
    assert (conn, kind, err) == (3, CLOSED, 0)


def test_requests_before_the_end_of_file_are_served_first(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    write = adu(1, 1, bytes.fromhex("06 0000 0001"))
    read = adu(2, 1, read_pdu(3, 0, 3))
    client.sendall(write + read + read[:4])  # and a partial one
    client.shutdown(socket.SHUT_WR)
    [(_, kind, _, got, _)] = engine.take()
    assert (kind, got) == (REQUEST, write)
    assert engine.take(SILENCE) == []  # CLOSED waits for the requests before it
    assert engine.send(0, write) == engine.lib.RTU_OK
    assert recv_adu(client) == write
    assert recv_adu(client) == image.answer(1, read)
    [(_, kind, err, _, _)] = engine.take()
    assert (kind, err) == (CLOSED, 0)


def test_a_socket_error_is_closed_with_its_errno(engine: Engine) -> None:
    client = socket.create_server(("127.0.0.1", 0))
    with client:
        peer = socket.create_connection(client.getsockname())
        server, _ = client.accept()
        fd = server.detach()
        assert engine.lib.rtu_serve_attach(engine.s, 0, fd, engine.routes, 0) == engine.lib.RTU_OK
        peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        peer.close()  # a reset
        [(_, kind, err, _, _)] = engine.take()
        assert kind == CLOSED and err in (errno.ECONNRESET, 0)


def test_a_client_that_never_reads_is_stalled() -> None:
    engine = Engine(max_unsent=600)
    try:
        engine.route(1, holding_image())
        client = engine.attach(0, sndbuf=4096)
        request = adu(1, 1, read_pdu(3, 0, 125))  # 259-byte answers
        client.sendall(request * 300)
        events = engine.take()
        assert [(c, k) for c, k, *_ in events] == [(0, STALLED)]
        st = engine.state(0)
        assert 600 < st.unsent <= engine.lib.RTU_SERVE_OUT_CAP
        answered = engine.stats()[1]
        assert answered == st.answered and 0 < answered < 300
    finally:
        engine.destroy()


def test_a_slow_reader_is_held_by_flow_control_not_stalled(engine: Engine) -> None:
    """max_unsent above the engine's output room: the engine stops reading the client
    while its answers wait, and goes on as it reads them, all in order."""
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0, sndbuf=4096)
    requests = [adu(i, 1, read_pdu(3, i % 76, 125)) for i in range(400)]
    sender = threading.Thread(target=client.sendall, args=(b"".join(requests),))
    sender.start()
    engine.until(lambda: engine.state(0).unsent > 0, "answers waiting unsent")
    assert engine.stats()[1] < 400  # not all answered: the socket does not take them
    for r in requests:
        assert recv_adu(client) == image.answer(1, r)
    sender.join(PATIENCE)
    assert engine.take(0) == [] and engine.stats()[:3] == (400, 400, 0)


# ------------------------------------------------------------ detach and destroy


def test_detach_closes_the_socket_and_drops_its_events(engine: Engine) -> None:
    lib = engine.lib
    keep = engine.attach(0)
    gone = engine.attach(1)
    gone.sendall(adu(1, 5, read_pdu(3, 0, 1)))  # handed over
    keep.sendall(adu(2, 5, read_pdu(3, 0, 1)))
    engine.until(lambda: engine.state(0).handed and engine.state(1).handed, "both handed")
    assert lib.rtu_serve_detach(engine.s, 1) == lib.RTU_OK
    assert gone.recv(16) == b""  # the peer sees the end of file
    events = engine.take()
    assert [(c, k) for c, k, *_ in events] == [(0, REQUEST)]
    assert lib.rtu_serve_detach(engine.s, 1) == lib.RTU_EINVAL
    assert lib.rtu_serve_conn(engine.s, 1, engine.ffi.new("rtu_serve_conn_state *")) == (
        lib.RTU_EINVAL
    )
    # the only event waiting dropped: the eventfd is no longer readable
    third = engine.attach(2)
    third.sendall(adu(3, 5, read_pdu(3, 0, 1)))
    engine.until(lambda: engine.waiting(), "the event")
    assert lib.rtu_serve_detach(engine.s, 2) == lib.RTU_OK
    assert not engine.waiting() and engine.take(0) == []
    # keep's request answered: none waits, so the image answers again
    assert engine.send(0, b"") == lib.RTU_OK
    # the slot again, on a new socket (its generation: nothing of the old one)
    image = holding_image()
    engine.route(5, image)
    again = engine.attach(1)
    request = adu(4, 5, read_pdu(3, 0, 1))
    again.sendall(request)
    assert recv_adu(again) == image.answer(5, request)


def test_attach_refuses(engine: Engine) -> None:
    lib = engine.lib
    engine.attach(0)
    a, b = socket.socketpair()
    with a, b:
        assert (
            lib.rtu_serve_attach(engine.s, 0, b.fileno(), engine.routes, 0) == lib.RTU_EINVAL
        )  # busy
        assert (
            lib.rtu_serve_attach(engine.s, 4, b.fileno(), engine.routes, 0) == lib.RTU_EINVAL
        )  # capacity 4
        assert lib.rtu_serve_attach(engine.s, 1, -1, engine.routes, 0) == lib.RTU_EINVAL
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        assert lib.rtu_serve_attach(engine.s, 1, udp.fileno(), engine.routes, 0) == lib.RTU_EINVAL
    assert lib.rtu_serve_detach(engine.s, 3) == lib.RTU_EINVAL
    assert lib.rtu_serve_stats_get(engine.s, engine.ffi.NULL) == lib.RTU_EINVAL


def test_attach_refuses_routes_to_a_bad_image(engine: Engine) -> None:
    lib = engine.lib
    bad = Image([[], [], [(5, PLAIN, [1]), (0, PLAIN, [1])], []])  # unsorted
    engine.route(7, bad)
    a, b = socket.socketpair()
    with a, b:
        assert lib.rtu_serve_attach(engine.s, 0, b.fileno(), engine.routes, 0) == lib.RTU_EINVAL
        engine.route(7, None)
        assert lib.rtu_serve_attach(engine.s, 0, b.fileno(), engine.routes, 0) == lib.RTU_OK
        # no routes at all: every request is Python's
        c, d = socket.socketpair()
        with c:
            assert lib.rtu_serve_attach(engine.s, 1, d.detach(), engine.ffi.NULL, 0) == lib.RTU_OK
            request = adu(1, 1, read_pdu(3, 0, 1))
            c.sendall(request)
            [(conn, kind, _, got, _)] = engine.take()
            assert (conn, kind, got) == (1, REQUEST, request)
        assert lib.rtu_serve_detach(engine.s, 1) == lib.RTU_OK
        assert lib.rtu_serve_detach(engine.s, 0) == lib.RTU_OK
        b.detach()  # (the engine closed it)


def test_init_refuses_and_sizes() -> None:
    ffi, lib = _core()
    assert lib.rtu_serve_size(0) == 0 and lib.rtu_serve_size(65537) == 0
    assert lib.rtu_serve_size(65536) > lib.rtu_serve_size(1) > 0
    mem = ffi.new("uint64_t[]", lib.rtu_serve_size(1) // 8 + 1)
    s = ffi.cast("rtu_serve *", mem)
    assert lib.rtu_serve_init(s, 0, 100) == lib.RTU_EINVAL
    assert lib.rtu_serve_init(s, 1, 0) == lib.RTU_EINVAL
    assert lib.rtu_serve_init(ffi.NULL, 1, 100) == lib.RTU_EINVAL
    lib.rtu_serve_destroy(s)  # never set up: nothing
    assert lib.rtu_serve_fd(s) == -1 and lib.rtu_serve_errno(s) == 0
    assert lib.rtu_serve_init(s, 1, 100) == lib.RTU_OK
    assert lib.rtu_serve_init(s, 1, 100) == lib.RTU_EINVAL  # set up already
    lib.rtu_serve_destroy(s)


def test_destroy_joins_and_closes_every_socket() -> None:
    engine = Engine()
    image = holding_image()
    engine.route(1, image)
    clients = [engine.attach(i) for i in range(3)]
    request = adu(1, 1, read_pdu(3, 0, 1))
    clients[0].sendall(request)
    assert recv_adu(clients[0]) == image.answer(1, request)
    clients[1].sendall(adu(2, 2, read_pdu(3, 0, 1)))  # handed, never answered
    assert len(engine.take()) == 1
    engine.destroy()
    for c in clients:
        assert c.recv(16) == b""
    engine.destroy()  # twice: nothing
    assert engine.lib.rtu_serve_fd(engine.s) == -1
    assert engine.lib.rtu_serve_take(engine.s, engine.out, 16) == 0


# ------------------------------------------------------------ the images lock


def test_values_changed_under_the_lock_are_read_next(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    request = adu(1, 1, read_pdu(3, 0, 2))
    client.sendall(request)
    assert recv_adu(client)[-4:] == bytes.fromhex("0000 0101")
    values = image.arrays[2][0]
    engine.lib.rtu_images_lock()
    values[0], values[1] = 0xCAFE, 0xF00D
    engine.lib.rtu_images_unlock()
    client.sendall(request)
    assert recv_adu(client)[-4:] == bytes.fromhex("cafe f00d")


def test_no_torn_read_while_python_writes_pairs(engine: Engine) -> None:
    """A Python thread writes registers 0 and 1 as (x, x) under rtu_images_lock while
    the client reads both: the engine (which reads under the same lock) never answers
    two different values."""
    lib = engine.lib
    image = holding_image()
    engine.route(1, image)
    client = engine.attach(0)
    values = image.arrays[2][0]
    stop = threading.Event()
    writes = [0]

    def writer() -> None:
        x = 0
        while not stop.is_set():
            x = (x + 1) & 0xFFFF
            lib.rtu_images_lock()
            values[0] = x
            values[1] = x
            lib.rtu_images_unlock()
            writes[0] += 1

    thread = threading.Thread(target=writer)
    thread.start()
    seen = set()
    try:
        for i in range(3000):
            client.sendall(adu(i, 1, read_pdu(3, 0, 2)))
            a, b = struct.unpack(">HH", recv_adu(client)[-4:])
            assert a == b, (i, a, b)
            seen.add(a)
    finally:
        stop.set()
        thread.join(PATIENCE)
    assert writes[0] > 0 and len(seen) > 1


# ------------------------------------------------------------ TCP and stats


def test_loopback_tcp_and_exact_stats(engine: Engine) -> None:
    image = holding_image()
    engine.route(1, image)
    engine.route(0, image)
    with socket.create_server(("127.0.0.1", 0)) as listener:
        clients = []
        for conn in range(2):
            c = socket.create_connection(listener.getsockname(), timeout=PATIENCE)
            server, _ = listener.accept()
            assert (
                engine.lib.rtu_serve_attach(engine.s, conn, server.detach(), engine.routes, 0) == 0
            )
            clients.append(c)
        plan = [(1, 3), (0, 1), (1, 4), (0, 3), (9, 3)]  # (unit, fc); unit 9: Python's
        for conn, c in enumerate(clients):
            for tid, (unit, fc) in enumerate(plan):
                request = adu(tid, unit, read_pdu(fc, 0, 2))
                c.sendall(request)
                if unit == 9:
                    [(got_conn, kind, _, got, _)] = engine.take()
                    assert (got_conn, kind, got) == (conn, REQUEST, request)
                    assert engine.send(conn, got) == 0
                    assert recv_adu(c) == got
                else:
                    assert recv_adu(c) == image.answer(unit, request)
            st = engine.state(conn)  # this connection's own figures
            assert (st.answered, list(st.by_function)) == (4, [0, 1, 0, 2, 1])
            c.close()
            [(got_conn, kind, err, _, _)] = engine.take()
            assert (got_conn, kind, err) == (conn, CLOSED, 0)
    assert engine.stats() == (10, 8, 2, [0, 2, 0, 4, 2])


def test_while_a_request_waits_for_python_every_connection_hands_over(engine: Engine) -> None:
    """Requests run in the order they were read, across connections too: behind a
    request handed to Python, another connection's read is handed over as well, and
    the image answers again once every handed request is answered."""
    image = holding_image()
    engine.route(1, image)
    first, second = engine.attach(0), engine.attach(1)
    write = adu(1, 1, bytes([6, 0, 0, 0, 9]))
    read = adu(2, 1, read_pdu(3, 0, 1))
    first.sendall(write)
    [(conn, kind, _, got, _)] = engine.take()
    assert (conn, kind, got) == (0, REQUEST, write)
    second.sendall(read)
    [(conn, kind, _, got, _)] = engine.take()
    assert (conn, kind, got) == (1, REQUEST, read)  # behind the write: Python's
    assert engine.send(0, write) == engine.lib.RTU_OK
    assert engine.send(1, read) == engine.lib.RTU_OK
    assert recv_adu(first) == write and recv_adu(second) == read
    second.sendall(read)
    assert recv_adu(second) == image.answer(1, read)  # none waits: the image's
    assert engine.stats()[:3] == (3, 1, 2)
