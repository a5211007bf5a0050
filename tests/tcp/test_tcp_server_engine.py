"""`TcpServer`'s C engine (pyrtu/gateway/_engine.py, csrc/rtu_serve_io.c): plain reads
answered without Python, everything else as before.

Each test runs with the engine and without it (``engine=False``: every request in
Python), and expects the same from both; the engine's own figures say which
requests it answered.  Real clients on 127.0.0.1: pyrtu's masters, raw sockets
with requests built here with ``struct`` ([TCP] 3.1.3, [AP] 6.1-6.6)."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mbap_wire import read_adu

from pyrtu import ExceptionResponseError, Master
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.gateway import GatewayLimits
from pyrtu.protocol._image import available
from pyrtu.protocol.datastore import DataStore
from pyrtu.tcp.server import TcpServer

pytestmark = pytest.mark.skipif(not available(), reason="the C core has no engine here")

ENGINE = [pytest.param(True, id="engine"), pytest.param(False, id="python")]


def store_of(n: int = 100) -> DataStore:
    store = DataStore()
    store.holding_registers.add_range(0, [(i * 7) & 0xFFFF for i in range(n)])
    store.input_registers.add_range(0, [(i * 11) & 0xFFFF for i in range(n)])
    store.coils.add_range(0, [i % 3 == 0 for i in range(n)])
    store.discrete_inputs.add_range(0, [i % 5 == 0 for i in range(n)])
    return store


class Served:
    """A server on an event loop in a thread; ``calls``: the requests Python executed
    (`Gateway._request`, counted on the way through)."""

    def __init__(self, server: TcpServer) -> None:
        self.server = server
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.calls: list[bytes] = []
        gateway = server._gateway
        original = gateway._request

        def counted(conn: Any, transaction: int, unit: int, pdu: bytes) -> None:
            self.calls.append(pdu)
            original(conn, transaction, unit, pdu)

        gateway._request = counted  # type: ignore[method-assign]
        self.run(server.start("127.0.0.1", 0))
        assert server.address is not None
        self.address = server.address
        self.url = f"tcp://127.0.0.1:{server.address[1]}"

    def run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def call(self, fn: Any) -> Any:
        async def on_loop() -> Any:
            return fn()

        return self.run(on_loop())

    def close(self) -> None:
        self.run(self.server.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


@pytest.fixture
def serve() -> Iterator[Any]:
    made: list[Served] = []

    def start(server: TcpServer) -> Served:
        s = Served(server)
        made.append(s)
        return s

    yield start
    for s in made:
        s.close()


def request(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def connect(address: tuple[str, int]) -> socket.socket:
    s = socket.create_connection(address, timeout=5)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


@pytest.mark.parametrize("engine", ENGINE)
def test_reads_of_the_four_tables(serve: Any, engine: bool) -> None:
    store = store_of()
    s = serve(TcpServer.for_store(1, store, engine=engine))
    assert (s.server.engine_refused is None) == engine
    with Master(s.url, timeout=2.0) as m:
        for _ in range(3):
            assert m.read_holding_registers(1, 3, 10) == [(i * 7) & 0xFFFF for i in range(3, 13)]
            assert m.read_input_registers(1, 90, 10) == [(i * 11) & 0xFFFF for i in range(90, 100)]
            assert m.read_coils(1, 5, 17) == [i % 3 == 0 for i in range(5, 22)]
            assert m.read_discrete_inputs(1, 0, 100) == [i % 5 == 0 for i in range(100)]
            assert m.read_holding_registers(255, 0, 1) == [0]  # the device itself
    # the engine's reads never reached Python; without it, every one did
    assert len(s.calls) == (0 if engine else 15)
    stats = s.call(s.server.stats)
    assert stats["requests"] == stats["answers"] == 15
    assert stats["bus_transactions"] == [15]
    # FC 11's event counter counts them too ([AP] 6.9: successful requests)
    with Master(s.url, timeout=2.0) as m:
        assert m.get_comm_event_counter(1)[1] == 15


@pytest.mark.parametrize("engine", ENGINE)
def test_what_the_engine_does_not_answer_python_does(serve: Any, engine: bool) -> None:
    store = store_of()
    written: list[tuple[int, list[int]]] = []
    store.holding_registers.add_range(
        200, [0, 0], on_write=lambda a, v: written.append((a, list(v)))
    )
    store.input_registers.add_range(300, [5], on_read=lambda a, n: None)
    s = serve(TcpServer.for_store(1, store, engine=engine))
    with Master(s.url, timeout=2.0) as m:
        m.write_register(1, 200, 77)
        assert written == [(200, [77])]
        assert m.read_holding_registers(1, 200, 2) == [77, 0]
        assert m.read_input_registers(1, 300, 1) == [5]  # a range with on_read: Python's
        with pytest.raises(ExceptionResponseError) as e:
            m.read_holding_registers(1, 99, 2)  # past the range: exception 2
        assert e.value.code == 2
        with pytest.raises(ExceptionResponseError) as e:
            m.read_holding_registers(1, 150, 1)  # in no range
        assert e.value.code == 2
    handed = [p[0] for p in s.calls]
    if engine:  # the write, the read of the held range, the two exceptions
        assert handed == [6, 4, 3, 3]
    else:
        assert handed == [6, 3, 4, 3, 3]


@pytest.mark.parametrize("engine", ENGINE)
def test_quantity_bounds_exactly_at_them(serve: Any, engine: bool) -> None:
    """[AP] 6.1/6.3: 1..2000 bits, 1..125 registers; one past is exception 3."""
    store = DataStore()
    store.holding_registers.add_range(0, [1] * 200)
    store.coils.add_range(0, [True] * 2100)
    s = serve(TcpServer.for_store(1, store, engine=engine))
    sock = connect(s.address)
    try:
        for fc, quantity, expected in [
            (3, 125, bytes([3, 250]) + b"\x00\x01" * 125),
            (3, 126, bytes([0x83, 3])),
            (3, 0, bytes([0x83, 3])),
            (1, 2000, bytes([1, 250]) + b"\xff" * 250),
            (1, 2001, bytes([0x81, 3])),
        ]:
            sock.sendall(request(9, 1, struct.pack(">BHH", fc, 0, quantity)))
            answer = read_adu(sock)
            assert answer[:2] == b"\x00\x09" and answer[6] == 1
            assert answer[7:] == expected, (fc, quantity)
    finally:
        sock.close()


@pytest.mark.parametrize("engine", ENGINE)
def test_answers_keep_the_order_of_pipelined_requests(serve: Any, engine: bool) -> None:
    """A write the engine hands to Python and the reads sent behind it in one segment:
    the reads see the write, the answers come back in request order."""
    s = serve(TcpServer.for_store(1, store_of(), engine=engine))
    sock = connect(s.address)
    try:
        burst = b"".join(
            [
                request(1, 1, struct.pack(">BHH", 3, 10, 1)),
                request(2, 1, struct.pack(">BHH", 6, 10, 4242)),
                request(3, 1, struct.pack(">BHH", 3, 10, 1)),
                request(4, 1, struct.pack(">BHH", 4, 0, 2)),
                request(5, 1, struct.pack(">BHHBH", 16, 11, 1, 2, 99)),
                request(6, 1, struct.pack(">BHH", 3, 10, 2)),
            ]
        )
        sock.sendall(burst)
        answers = [read_adu(sock) for _ in range(6)]
    finally:
        sock.close()
    assert [struct.unpack_from(">H", a)[0] for a in answers] == [1, 2, 3, 4, 5, 6]
    assert answers[0][7:] == bytes([3, 2]) + struct.pack(">H", 70)
    assert answers[1][7:] == struct.pack(">BHH", 6, 10, 4242)
    assert answers[2][7:] == bytes([3, 2]) + struct.pack(">H", 4242)
    assert answers[3][7:] == bytes([4, 4]) + struct.pack(">HH", 0, 11)
    assert answers[4][7:] == struct.pack(">BHH", 16, 11, 1)
    assert answers[5][7:] == bytes([3, 4]) + struct.pack(">HH", 4242, 99)


TABLES = ["coils", "discrete_inputs", "holding_registers", "input_registers"]


@pytest.mark.parametrize("engine", ENGINE)
@pytest.mark.parametrize("table", TABLES)
def test_a_change_to_any_one_table_is_read_at_once(serve: Any, engine: bool, table: str) -> None:
    """The owner changes one value of one table (the others untouched); the next
    read of that table answers the new value, for each of the four tables."""
    store = store_of()
    s = serve(TcpServer.for_store(1, store, engine=engine))
    read: Any = {
        "coils": Master.read_coils,
        "discrete_inputs": Master.read_discrete_inputs,
        "holding_registers": Master.read_holding_registers,
        "input_registers": Master.read_input_registers,
    }[table]
    bits = table in ("coils", "discrete_inputs")
    with Master(s.url, timeout=2.0) as m:
        before = read(m, 1, 7, 1)[0]
        new: bool | int = (not before) if bits else (int(before) + 1) & 0xFFFF
        with store.lock:
            getattr(store, table).set(7, new)
        assert read(m, 1, 7, 1) == [new]


@pytest.mark.parametrize("engine", ENGINE)
def test_a_change_made_under_the_lock_is_seen_whole(serve: Any, engine: bool) -> None:
    """The owner changes two registers together, under the store's lock, while a
    client reads both: it never sees one changed without the other."""
    store = store_of()
    s = serve(TcpServer.for_store(1, store, engine=engine))
    stop = threading.Event()

    def writer() -> None:
        x = 0
        while not stop.is_set():
            x = (x + 1) & 0xFFFF
            with store.lock:
                store.holding_registers.set(20, x)
                store.holding_registers.set(21, x)

    t = threading.Thread(target=writer)
    t.start()
    seen = set()
    try:
        with Master(s.url, timeout=2.0) as m:
            for _ in range(300):
                a, b = m.read_holding_registers(1, 20, 2)
                assert a == b
                seen.add(a)
    finally:
        stop.set()
        t.join(10)
    assert len(seen) > 1  # (the values did change meanwhile)


@pytest.mark.parametrize("engine", ENGINE)
def test_listen_only_and_hooks_take_effect_at_once(serve: Any, engine: bool) -> None:
    """FC 08 sub-function 04 ([AP] 6.8.1: listen-only mode) is executed by Python (a
    TCP server's slave answers nothing to it: exception 0x0B from the gateway); the
    read pipelined right behind it is Python's too, as every request while the mode
    holds; a hook added later sees every request."""
    store = store_of()
    s = serve(TcpServer.for_store(1, store, engine=engine))
    sock = connect(s.address)
    try:
        sock.sendall(
            request(1, 1, struct.pack(">BHH", 8, 4, 0))
            + request(2, 1, struct.pack(">BHH", 3, 0, 1))
        )
        first, second = read_adu(sock), read_adu(sock)
    finally:
        sock.close()
    assert first == request(1, 1, bytes([0x88, 0x0B]))
    assert second == request(2, 1, bytes([3, 2, 0, 0]))
    assert [p[0] for p in s.calls] == [8, 3]
    assert s.call(lambda: s.server.app.listen_only)
    seen: list[bytes] = []
    s.call(lambda: s.server.app.on_request(lambda unit, pdu: seen.append(pdu)))
    s.call(lambda: setattr(s.server.app.line, "listen_only", False))
    with Master(s.url, timeout=2.0) as m:
        assert m.read_holding_registers(1, 1, 1) == [7]
    assert seen == [bytes.fromhex("0300010001")]
    assert [p[0] for p in s.calls] == [8, 3, 3]


@pytest.mark.parametrize("engine", ENGINE)
def test_a_bad_header_closes_that_connection_only(serve: Any, engine: bool) -> None:
    s = serve(TcpServer.for_store(1, store_of(), engine=engine))
    bad = connect(s.address)
    with Master(s.url, timeout=2.0) as m:
        bad.sendall(struct.pack(">HHHB", 1, 1, 6, 1) + struct.pack(">BHH", 3, 0, 1))  # protocol 1
        bad.settimeout(5)
        assert bad.recv(100) == b""  # closed
        bad.close()
        assert m.read_holding_registers(1, 2, 1) == [14]
    counters = s.call(lambda: s.server.counters)
    assert counters["bad_headers"] == 1


@pytest.mark.parametrize("engine", ENGINE)
def test_the_table_frees_closed_and_silent_connections(serve: Any, engine: bool) -> None:
    """A client that closes leaves the table; one that stops talking is closed by the
    idle timeout, one that sends half a request by the header timeout; a full
    table gives the idle one's slot to a newcomer."""
    limits = GatewayLimits(max_connections=2, idle_timeout=0.4, header_timeout=0.4)
    s = serve(TcpServer.for_store(1, store_of(), limits, engine=engine))
    a = connect(s.address)
    a.sendall(request(1, 1, struct.pack(">BHH", 3, 0, 1)))
    read_adu(a)
    a.close()
    deadline = time.monotonic() + 5
    while s.call(lambda: s.server.stats()["open_connections"]) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert s.call(lambda: s.server.stats()["open_connections"]) == 0
    idle, half = connect(s.address), connect(s.address)
    idle.sendall(request(2, 1, struct.pack(">BHH", 3, 0, 1)))
    read_adu(idle)
    half.sendall(request(3, 1, struct.pack(">BHH", 3, 0, 1))[:5])
    idle.settimeout(5)
    half.settimeout(5)
    assert half.recv(10) == b""  # the header timeout
    assert idle.recv(10) == b""  # the idle timeout
    counters = s.call(lambda: s.server.counters)
    assert counters["header_timeouts"] == 1 and counters["idle_timeouts"] == 1
    idle.close()
    half.close()


@pytest.mark.parametrize("engine", ENGINE)
def test_a_newcomer_takes_the_slot_of_the_idle_one(serve: Any, engine: bool) -> None:
    limits = GatewayLimits(max_connections=1, idle_timeout=0, header_timeout=0)
    s = serve(TcpServer.for_store(1, store_of(), limits, engine=engine))
    old = connect(s.address)
    old.sendall(request(1, 1, struct.pack(">BHH", 3, 0, 1)))
    read_adu(old)
    with Master(s.url, timeout=2.0) as m:
        assert m.read_holding_registers(1, 3, 1) == [21]
    old.settimeout(5)
    assert old.recv(10) == b""
    old.close()
    assert s.call(lambda: s.server.counters)["evicted"] == 1


@pytest.mark.parametrize("engine", ENGINE)
def test_an_async_master_pipelining_reads_and_writes(serve: Any, engine: bool) -> None:
    store = store_of()
    s = serve(TcpServer.for_store(1, store, engine=engine))

    async def go() -> list[Any]:
        async with AsyncMaster(s.url, timeout=2.0, max_in_flight=8) as m:
            out: list[Any] = []
            for k in range(20):
                out += await asyncio.gather(
                    m.write_register(1, 50, k),
                    m.read_holding_registers(1, 50, 1),
                    m.read_input_registers(1, 1, 2),
                    m.read_coils(1, 0, 4),
                )
            return out

    got = asyncio.run(go())
    for k in range(20):
        assert got[4 * k + 1] == [k]  # the write ahead of it, on the same connection
        assert got[4 * k + 2] == [11, 22]
        assert got[4 * k + 3] == [True, False, False, True]
    assert store.holding_registers.get(50) == 19


def test_engine_refused_says_why() -> None:
    assert TcpServer.for_store(1, store_of(), engine=False).engine_refused == "engine=False"
    twin = TcpServer.for_store(1, store_of(), backend="python")
    assert twin.engine_refused == "the slave runs on the pure-Python backend"
    custom = TcpServer.for_store(1, store_of())
    assert custom.engine_refused is None
    with pytest.raises(TypeError, match="engine"):
        TcpServer.for_store(1, store_of(), engine=1)  # type: ignore[arg-type]


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def test_the_servers_of_a_loop_share_one_engine_that_stops_with_the_last(serve: Any) -> None:
    first = serve(TcpServer.for_store(1, store_of()))
    with_one = _threads()  # (with the first server's engine)
    second = TcpServer.for_store(2, store_of(10))
    first.run(second.start("127.0.0.1", 0))
    assert _threads() == with_one  # no second engine
    engines = [s._gateway.engine for s in (first.server, second)]
    assert engines[0] is not None and engines[1] is not None
    assert engines[0].engine is engines[1].engine
    assert second.address is not None
    with (
        Master(first.url, timeout=2.0) as a,
        Master(f"tcp://127.0.0.1:{second.address[1]}", timeout=2.0) as b,
    ):
        assert a.read_holding_registers(1, 1, 1) == [7]
        assert b.read_holding_registers(2, 9, 1) == [63]
        with pytest.raises(ExceptionResponseError):
            b.read_holding_registers(1, 0, 1)  # unit 1 is the first server's, not its
    first.run(second.close())
    assert not engines[0].engine.closed  # the first server still uses it
    first.run(first.server.close())
    assert engines[0].engine.closed
    assert _threads() == with_one - 1  # the engine's thread joined


def test_a_server_that_hands_everything_to_python_serves_without_the_engine(serve: Any) -> None:
    """A slave with an ``on_request`` hook (as `pyrtu simulate`'s drives have) when the
    client connects: its connection is asyncio's, as without an engine."""
    server = TcpServer.for_store(1, store_of())
    seen: list[bytes] = []
    server.app.on_request(lambda unit, pdu: seen.append(pdu))
    s = serve(server)
    engine = s.server._gateway.engine
    assert engine is not None
    with Master(s.url, timeout=2.0) as m:
        assert m.read_holding_registers(1, 2, 1) == [14]
        assert s.call(lambda: len(engine.conns)) == 0  # connected, not the engine's
        assert s.call(lambda: s.server.stats()["open_connections"]) == 1
    assert seen == [bytes.fromhex("0300020001")]


def test_a_slave_whose_reads_are_its_own_is_not_served_by_the_engine() -> None:
    custom = TcpServer.for_store(1, store_of())
    custom.app.register_function(3, lambda slave, unit, pdu: bytes([3, 2, 0, 1]))
    assert TcpServer(custom.app).engine_refused == "function 3 is the application's own"
    narrow = TcpServer.for_store(1, store_of(), functions={3, 4, 6, 16})
    assert narrow.engine_refused == "function 1 is not served"


@pytest.mark.parametrize("engine", ENGINE)
def test_a_client_that_never_reads_its_answers_is_reset(serve: Any, engine: bool) -> None:
    """The gateway's ``slow_clients``: a client that sends and never reads is reset,
    with the engine as without it; the others go on."""
    s = serve(TcpServer.for_store(1, store_of(), engine=engine))
    stuck = socket.socket()
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    stuck.connect(s.address)
    stuck.setblocking(False)
    burst = request(1, 1, struct.pack(">BHH", 3, 0, 125)) * 64  # 259-byte answers
    view, at, reset = memoryview(burst), 0, False
    give_up = time.monotonic() + 30
    while time.monotonic() < give_up and not reset:
        try:
            at = (at + stuck.send(view[at:])) % len(burst)  # (whole requests, in order)
        except BlockingIOError:
            time.sleep(0.005)
        except (ConnectionResetError, BrokenPipeError):
            reset = True
    stuck.close()
    assert reset, "the client that never reads was not reset"
    assert s.call(lambda: s.server.counters)["slow_clients"] == 1
    with Master(s.url, timeout=2.0) as m:
        assert m.read_holding_registers(1, 4, 1) == [28]


@pytest.mark.wall_clock
@pytest.mark.parametrize("engine", ENGINE)
def test_a_client_that_talks_is_not_closed_as_idle(serve: Any, engine: bool) -> None:
    """Idle timeout 0.5 s: a client reading (answered by the engine) or writing
    (answered by Python) every 0.1 s for 1.5 s keeps its connection; silent, it
    loses it within the timeout and a sweep."""
    limits = GatewayLimits(idle_timeout=0.5, header_timeout=0)
    s = serve(TcpServer.for_store(1, store_of(), limits, engine=engine))
    for pdu in (struct.pack(">BHH", 3, 0, 1), struct.pack(">BHH", 6, 30, 5)):
        sock = connect(s.address)
        try:
            end = time.monotonic() + 1.5
            tid = 0
            while time.monotonic() < end:
                tid += 1
                sock.sendall(request(tid, 1, pdu))
                assert read_adu(sock)[:2] == struct.pack(">H", tid)  # still served
                time.sleep(0.1)
            sock.settimeout(3)
            assert sock.recv(10) == b""  # silent now: closed
        finally:
            sock.close()
    assert s.call(lambda: s.server.counters)["idle_timeouts"] == 2


def test_the_figures_count_what_the_engine_answered_while_connected(serve: Any) -> None:
    store = store_of()
    s = serve(TcpServer.for_store(1, store))
    with Master(s.url, timeout=2.0) as m:
        for _ in range(3):
            m.read_holding_registers(1, 0, 2)
        first = s.call(s.server.stats)
        m.read_coils(1, 0, 8)
        m.read_input_registers(1, 0, 1)
        second = s.call(s.server.stats)
        assert m.get_comm_event_counter(1)[1] == 5  # FC 11, Python's: the 5 before it
    assert s.calls == [bytes([11])]
    assert (first["requests"], first["answers"], first["bus_transactions"]) == (3, 3, [3])
    assert (second["requests"], second["answers"], second["bus_transactions"]) == (5, 5, [5])
    counters = s.call(lambda: s.server.counters)
    assert (counters["requests"], counters["answers"]) == (6, 6)  # FC 11 too


@pytest.mark.parametrize("engine", ENGINE)
def test_debug_logging_shows_every_frame(
    serve: Any, engine: bool, caplog: pytest.LogCaptureFixture
) -> None:
    s = serve(TcpServer.for_store(1, store_of(), engine=engine))
    with caplog.at_level(logging.DEBUG, logger="pyrtu.gateway"):
        sock = connect(s.address)
        try:
            sock.sendall(request(5, 1, struct.pack(">BHH", 3, 0, 1)))
            assert read_adu(sock) == request(5, 1, bytes([3, 2, 0, 0]))
            s.call(lambda: None)  # (the loop's callback that wrote it has ended)
        finally:
            sock.close()
    rx = "RX unit 1: 00 05 00 00 00 06 01 03 00 00 00 01"
    tx = "TX unit 1: 00 05 00 00 00 05 01 03 02 00 00"
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.endswith(rx) for m in messages) and any(m.endswith(tx) for m in messages)


def test_an_audit_trail_or_a_policy_keeps_every_request_in_python(
    serve: Any, tmp_path: Path
) -> None:
    from pyrtu.security.audit import AuditTrail
    from pyrtu.security.policy import Policy

    trail = AuditTrail.open(tmp_path / "audit.jsonl")
    audited = serve(TcpServer.for_store(1, store_of(), audit=trail))
    policed = serve(TcpServer.for_store(1, store_of(), policy=Policy.read_only()))
    for s in (audited, policed):
        with Master(s.url, timeout=2.0) as m:
            assert m.read_holding_registers(1, 1, 1) == [7]
        assert s.calls == [bytes.fromhex("0300010001")]
    trail.close()


def test_the_engine_forgets_its_loop_once_stopped(serve: Any) -> None:
    from pyrtu.gateway._engine import Engine

    s = serve(TcpServer.for_store(1, store_of()))
    engine = s.server._gateway.engine
    assert engine is not None and Engine._by_loop.get(s.loop) is engine.engine
    fd = engine.engine._lib.rtu_serve_fd(engine.engine._s)
    s.run(s.server.close())
    assert Engine._by_loop.get(s.loop) is None
    assert engine.engine not in Engine._running
    # the loop no longer watches the engine's descriptor (closed with it)
    assert s.call(lambda: s.loop.remove_reader(fd)) is False


def test_connections_past_the_engine_s_slots_are_served_by_python(
    serve: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pyrtu.gateway import _engine

    monkeypatch.setattr(_engine, "CAPACITY", 2)
    s = serve(TcpServer.for_store(1, store_of()))
    socks = [connect(s.address) for _ in range(3)]
    try:
        for i, sock in enumerate(socks):
            sock.sendall(request(i, 1, struct.pack(">BHH", 3, 2, 1)))
            assert read_adu(sock) == request(i, 1, bytes([3, 2, 0, 14]))
    finally:
        for sock in socks:
            sock.close()
    assert len(s.calls) == 1  # the third, past the 2 slots


@pytest.mark.parametrize("engine", ENGINE)
def test_a_read_behind_a_write_on_another_connection_sees_it(serve: Any, engine: bool) -> None:
    """Requests are executed in the order they are read, across connections too: a
    write Python executes slowly (its ``on_write`` takes 0.2 s), and a read of the
    same register sent on another connection while it runs, answers the new value."""
    store = store_of()
    store.holding_registers.add_range(400, [1], on_write=lambda a, v: time.sleep(0.2))
    s = serve(TcpServer.for_store(1, store, engine=engine))
    writer, reader = connect(s.address), connect(s.address)
    try:
        writer.sendall(request(1, 1, struct.pack(">BHH", 6, 400, 2)))
        time.sleep(0.05)  # (the write is under way)
        reader.sendall(request(2, 1, struct.pack(">BHH", 3, 400, 1)))
        assert read_adu(reader) == request(2, 1, bytes([3, 2, 0, 2]))
        assert read_adu(writer) == request(1, 1, struct.pack(">BHH", 6, 400, 2))
    finally:
        writer.close()
        reader.close()


def test_a_server_whose_loop_closed_without_closing_it_is_stopped_by_the_next(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A server left running when its event loop ends (never closed) keeps its
    engine's memory and thread until the next engine starts, which stops it: its
    client sees the connection closed, and the new server answers."""
    import gc

    from pyrtu.gateway._engine import Engine

    store = store_of()
    client: list[socket.socket] = []

    async def started() -> None:
        loop = asyncio.get_running_loop()
        server = await TcpServer.for_store(1, store).start("127.0.0.1", 0)
        assert server.address is not None and server.engine_refused is None
        sock = await loop.run_in_executor(None, connect, server.address)
        client.append(sock)
        await loop.run_in_executor(None, sock.sendall, request(1, 1, struct.pack(">BHH", 3, 1, 1)))
        answer = await loop.run_in_executor(None, read_adu, sock)
        assert answer == request(1, 1, bytes([3, 2, 0, 7]))

    asyncio.run(started())  # (its tasks cancelled, the loop closed: the server never)
    gc.collect()  # (the loop, its server and the engine's Python side: only `_running` holds it)
    (old,) = [e for e in Engine._running if e._loop.is_closed()]
    (conn,) = old._conns.values()
    with_old = _threads()
    sock = client[0]
    try:
        # the old engine still answers from its memory (not freed under its thread)
        sock.sendall(request(2, 1, struct.pack(">BHH", 3, 1, 1)))
        assert read_adu(sock) == request(2, 1, bytes([3, 2, 0, 7]))

        async def again() -> list[int]:
            server = await TcpServer.for_store(1, store).start("127.0.0.1", 0)
            try:
                async with AsyncMaster(f"tcp://127.0.0.1:{server.address[1]}") as m:
                    return await m.read_holding_registers(1, 2, 1)
            finally:
                await server.close()

        with caplog.at_level(logging.WARNING, logger="pyrtu.gateway"):
            assert asyncio.run(again()) == [14]
        assert old.closed and old not in Engine._running and conn.closed
        assert "outlived its event loop" in caplog.text and "1 connection(s)" in caplog.text
        assert sock.recv(1) == b""  # its connection closed
    finally:
        sock.close()
    assert _threads() == with_old - 1  # the old engine's thread joined, the new one's too


@pytest.mark.parametrize("engine", ENGINE)
@pytest.mark.parametrize("partial", [True, False], ids=["part-of-a-request", "whole-requests"])
def test_requests_sent_with_the_connect_are_answered(
    serve: Any, engine: bool, partial: bool
) -> None:
    """Bytes the client sends before the server has even accepted it (its loop busy
    meanwhile): part of a request (the rest follows), or two whole requests.  Every
    request is answered once, in order, and the connection goes on being answered.
    asyncio reads none of them: the hand-over on the loop's next turn comes before
    its first read (a selector loop's reader is queued behind it and cancelled by
    the pause), so the engine answers them all."""
    s = serve(TcpServer.for_store(1, store_of(), engine=engine))
    wire = request(1, 1, struct.pack(">BHH", 3, 1, 1)) + request(2, 1, struct.pack(">BHH", 4, 2, 1))
    busy = asyncio.run_coroutine_threadsafe(_block(0.3), s.loop)  # (nothing accepted)
    time.sleep(0.05)
    sock = socket.create_connection(s.address, timeout=5)
    try:
        sock.sendall(wire[:6] if partial else wire)
        busy.result(5)
        if partial:
            time.sleep(0.05)
            sock.sendall(wire[6:])
        assert read_adu(sock) == request(1, 1, bytes([3, 2, 0, 7]))
        assert read_adu(sock) == request(2, 1, bytes([4, 2, 0, 22]))
        sock.sendall(request(3, 1, struct.pack(">BHH", 3, 9, 1)))
        assert read_adu(sock) == request(3, 1, bytes([3, 2, 0, 63]))
    finally:
        sock.close()
    assert [p[0] for p in s.calls] == ([] if engine else [3, 4, 3])


async def _block(seconds: float) -> None:
    """Hold the event loop (no callback of it runs) for ``seconds``."""
    time.sleep(seconds)
