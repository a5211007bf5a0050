"""The gateway: its sans-I/O queue and routes, and the asyncio gateway with real
peers behind it (a libmodbus TCP server as the bus here; the serial buses are in
test_gateway_serial.py).  Loopback addresses only."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from peers import pattern
from peers.tools import PeerBinaries, free_tcp_port, libmodbus_server
from tcp_helpers import flood, stuck_socket

from pyrtu import ExceptionResponseError, encode_mbap, parse_tcp_stream, pdu
from pyrtu.gateway import FairQueue, Gateway, GatewayLimits, Job, QueueFull, Routes, parse_units
from pyrtu.tcp import AsyncTcpClient

pytest_plugins = ["peers.fixtures"]

READ = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 4)


# -- sans-I/O parts ------------------------------------------------------------------


def job(conn: int, n: int) -> Job:
    return Job(conn=conn, transaction=n, unit=1, slave=1, pdu=READ)


def test_fair_queue_serves_connections_round_robin() -> None:
    q = FairQueue(max_per_connection=10, max_total=100)
    for n in range(5):
        q.submit(job(1, n))  # a client that pipelines five
    q.submit(job(2, 100))
    q.submit(job(3, 200))
    q.submit(job(2, 101))
    order = []
    while (j := q.pop()) is not None:
        order.append((j.conn, j.transaction))
    assert order == [(1, 0), (2, 100), (3, 200), (1, 1), (2, 101), (1, 2), (1, 3), (1, 4)]
    assert len(q) == 0


def test_fair_queue_bounds_and_drop() -> None:
    q = FairQueue(max_per_connection=2, max_total=3)
    q.submit(job(1, 0))
    q.submit(job(1, 1))
    with pytest.raises(QueueFull, match="connection 1"):
        q.submit(job(1, 2))
    q.submit(job(2, 0))
    with pytest.raises(QueueFull, match="wait for this bus"):
        q.submit(job(3, 0))
    assert q.queued(1) == 2 and q.drop(1) == 2 and len(q) == 1 and q.queued(1) == 0
    q.submit(job(3, 0))
    assert [q.pop().conn, q.pop().conn, q.pop()] == [2, 3, None]  # type: ignore[union-attr]


def test_routes_and_unit_ranges() -> None:
    assert parse_units("1-3,10, 0x20") == {1, 2, 3, 10, 32}
    for bad in ("0", "5-2", "1-248", "x", "1-"):
        with pytest.raises(ValueError, match="unit ids"):
            parse_units(bad)
    r = Routes([parse_units("1-10"), {11: 11, 255: 12}])
    assert [r.route(u) for u in (1, 11, 255, 3)] == [(0, 1), (1, 11), (1, 12), (0, 3)]
    assert r.route(21) is None and r.route(0) is None  # 0, the broadcast, goes to every bus
    with pytest.raises(ValueError, match="unit id 5 is on bus 0 and bus 1"):
        Routes([parse_units("1-10"), parse_units("5")])


def test_limits_are_validated() -> None:
    with pytest.raises(ValueError, match="max_connections"):
        GatewayLimits(max_connections=0)
    with pytest.raises(TypeError, match="max_write_buffer"):
        GatewayLimits(max_write_buffer=True)  # type: ignore[arg-type]
    for grace in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="close_grace"):
            GatewayLimits(close_grace=grace)
    for grace in (True, "5"):
        with pytest.raises(TypeError, match="close_grace"):
            GatewayLimits(close_grace=grace)  # type: ignore[arg-type]
    assert GatewayLimits(close_grace=0).close_grace == 0
    with pytest.raises(ValueError, match="at least one bus"):
        Gateway([])


# -- the asyncio gateway, a libmodbus TCP server behind it ---------------------------


async def open_gateway(
    buses: list[tuple[str, str]], limits: GatewayLimits | None = None, timeout: float = 1.0
) -> tuple[Gateway, list[AsyncTcpClient]]:
    clients = [
        await AsyncTcpClient.connect(url, timeout=timeout, max_in_flight=1) for url, _ in buses
    ]
    gw = Gateway(
        [(c, parse_units(units)) for c, (_, units) in zip(clients, buses, strict=True)], limits
    )
    await gw.start("127.0.0.1", 0)
    return gw, clients


async def shut(gw: Gateway, clients: list[AsyncTcpClient]) -> None:
    """Close the gateway, then the bus clients `open_gateway` made."""
    await gw.close()
    for c in clients:
        await c.close()


async def raw(gw: Gateway) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    assert gw.address is not None
    return await asyncio.open_connection(*gw.address)


async def until(check: object, timeout: float = 10.0) -> None:
    """Wait (polling) until ``check()`` is true: state, not a timed assertion."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not check():  # type: ignore[operator]
        assert loop.time() < end, "the gateway did not get there"
        await asyncio.sleep(0.01)


async def read_adu(reader: asyncio.StreamReader, timeout: float = 3.0) -> bytes:
    head = await asyncio.wait_for(reader.readexactly(6), timeout)
    (length,) = struct.unpack(">H", head[4:6])
    return head + await asyncio.wait_for(reader.readexactly(length), timeout)


@pytest.fixture
def run() -> Iterator[object]:
    loop = asyncio.new_event_loop()
    yield loop.run_until_complete
    loop.close()


def test_forwarding_preserves_transaction_and_unit_ids(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1-5")])
        reader, writer = await raw(gw)
        requests = [(0xBEEF, 1, READ), (0x0000, 5, READ), (0xFFFF, 2, pdu.read_request(1, 3, 9))]
        writer.write(b"".join(encode_mbap(*r) for r in requests))  # three in one write
        answers = [await read_adu(reader) for _ in requests]
        got = [(a.transaction, a.unit) for a in parse_tcp_stream(b"".join(answers), "master")]
        assert got == [(0xBEEF, 1), (0x0000, 5), (0xFFFF, 2)]
        first = parse_tcp_stream(answers[0], "master")[0]
        assert pdu.parse_registers(first.pdu, 4) == pattern.holdings(1, 0, 4)
        writer.close()
        await shut(gw, clients)

    run(main())


def test_unrouted_unit_gets_0x0a_and_broadcast_gets_nothing(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1-5")])
        assert gw.address is not None
        c = await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}", timeout=2.0)
        with pytest.raises(ExceptionResponseError) as info:
            await c.request(9, READ)
        assert info.value.code == 0x0A
        reader, writer = await raw(gw)
        writer.write(encode_mbap(5, 1, b"\x00\x01") + encode_mbap(6, 1, b"\x85\x01"))
        bad = parse_tcp_stream(await read_adu(reader) + await read_adu(reader), "master")
        assert [(f.transaction, f.function, f.exception_code) for f in bad] == [
            (5, 0x80, 1),
            (6, 0x85, 1),
        ]  # not function codes: illegal function, and the bus never saw them
        writer.close()
        assert await c.request(0, pdu.write_register_request(40, 4321)) is None
        await asyncio.sleep(0.2)  # nothing comes back; the write reached the bus
        got = await c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 40, 1))
        assert got is not None and pdu.parse_registers(got, 1) == [4321]
        assert c.counters["late"] == 0 and gw.counters["broadcasts"] == 1
        await c.close()
        await shut(gw, clients)

    run(main())


def test_dead_device_gets_0x0b_and_others_go_on(
    libmodbus_tcp: str,
    silent_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    async def main() -> None:
        # a long bus timeout: the live bus must finish its work while the dead one waits
        gw, clients = await open_gateway([(libmodbus_tcp, "1"), (silent_tcp, "20")], timeout=5.0)
        assert gw.address is not None
        url = f"tcp://{gw.address[0]}:{gw.address[1]}"
        dead = await AsyncTcpClient.connect(url, timeout=30.0)
        alive = await AsyncTcpClient.connect(url, timeout=30.0)
        dead_task = asyncio.ensure_future(dead.request(20, READ))
        answers = await asyncio.gather(*(alive.request(1, READ) for _ in range(30)))
        assert all(a is not None for a in answers)
        assert not dead_task.done()  # the live bus did not wait for the dead one
        with pytest.raises(ExceptionResponseError) as info:
            await dead_task
        assert info.value.code == 0x0B
        assert gw.counters["timeouts"] == 1
        for c in (dead, alive, *clients):
            await c.close()
        await gw.close()

    run(main())


@pytest.mark.parametrize(
    "header",
    ["0001 0001 0006 01", "0001 0000 00ff 01", "0001 0000 0001 01", "0001 0000 ffff 01"],
)
def test_bad_header_closes_that_connection_only(libmodbus_tcp: str, header: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1")])
        good_r, good_w = await raw(gw)
        bad_r, bad_w = await raw(gw)
        bad_w.write(encode_mbap(1, 1, READ) + bytes.fromhex(header) + READ)
        # closed at once: the good request before the bad header goes unanswered
        assert await asyncio.wait_for(bad_r.read(), 3.0) == b""
        good_w.write(encode_mbap(7, 1, READ))
        assert (await read_adu(good_r))[:2] == b"\x00\x07"
        assert gw.counters["bad_headers"] == 1
        good_w.close()
        await shut(gw, clients)

    run(main())


def test_bad_header_after_answered_requests_lets_them_be_read(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    """Answers written before a malformed header still reach a client that reads
    them (within close_grace); then the connection ends."""

    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1")])
        r, w = await raw(gw)
        w.write(b"".join(encode_mbap(n, 1, READ) for n in range(3)))
        await until(lambda: gw.counters["answers"] == 3)
        w.write(bytes.fromhex("0009 0001 0006 01") + READ)  # protocol id 1
        got = [parse_tcp_stream(await read_adu(r), "master")[0] for _ in range(3)]
        assert [a.transaction for a in got] == [0, 1, 2]
        assert all(pdu.parse_registers(a.pdu, 4) == pattern.holdings(1, 0, 4) for a in got)
        assert await asyncio.wait_for(r.read(), 3.0) == b""
        assert gw.counters["bad_headers"] == 1 and gw.counters["slow_clients"] == 0
        w.close()
        await shut(gw, clients)

    run(main())


def test_bad_header_from_a_client_that_never_reads_is_reset_after_the_grace(
    libmodbus_tcp: str, run
) -> None:  # type: ignore[no-untyped-def]
    """A client closed for a malformed header while answers to it wait unsent in the
    gateway, and that never reads them, is reset after close_grace: asyncio's close
    alone waits for the buffer to drain, so it held the connection forever."""

    async def main() -> None:
        limits = GatewayLimits(max_write_buffer=1 << 20, close_grace=0.2)
        gw, clients = await open_gateway([(libmodbus_tcp, "1")], limits)
        assert gw.address is not None
        stuck = stuck_socket(gw.address)
        big = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 125)  # 259-byte answers
        burst = b"".join(encode_mbap(n, 1, big) for n in range(16))  # one queue's worth
        loop = asyncio.get_running_loop()
        end = loop.time() + 20.0
        while not gw.stats()["unsent_bytes"]:  # until the kernel's buffers are full
            assert loop.time() < end, "the gateway's write buffer never filled"
            target = gw.counters["answers"] + 16
            await loop.sock_sendall(stuck, burst)
            await until(lambda t=target: gw.counters["answers"] >= t)  # type: ignore[misc]
        await loop.sock_sendall(stuck, bytes.fromhex("0009 0001 0006 01") + READ)
        await until(lambda: gw.counters["bad_headers"] == 1)
        assert gw.stats()["open_connections"] == 0  # it no longer counts
        await flood(stuck, encode_mbap(1, 1, READ), until_closed=10.0)  # reset, not kept
        stuck.close()
        assert gw.counters["slow_clients"] == 0
        async with await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}") as ok:
            assert pdu.parse_registers(await ok.request(1, READ) or b"", 4) == pattern.holdings(
                1, 0, 4
            )
        await shut(gw, clients)

    run(main())


def test_queue_overflow_answers_busy(silent_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        limits = GatewayLimits(max_queued_per_connection=2)
        gw, clients = await open_gateway([(silent_tcp, "1")], limits, timeout=0.5)
        reader, writer = await raw(gw)
        writer.write(encode_mbap(0, 1, READ))
        await until(lambda: gw.stats()["requests"] == 1 and gw.stats()["queued"] == [0])
        writer.write(b"".join(encode_mbap(n, 1, READ) for n in range(1, 6)))
        # one on the bus, two waiting, three refused at once with 0x06
        busy = [parse_tcp_stream(await read_adu(reader), "master")[0] for _ in range(3)]
        assert [(b.transaction, b.function, b.exception_code) for b in busy] == [
            (3, 0x83, 6),
            (4, 0x83, 6),
            (5, 0x83, 6),
        ]
        # the three accepted ones time out on the dead bus: 0x0B, in order
        later = [parse_tcp_stream(await read_adu(reader, 3.0), "master")[0] for _ in range(3)]
        assert [(b.transaction, b.exception_code) for b in later] == [(0, 11), (1, 11), (2, 11)]
        assert gw.counters["busy"] == 3
        writer.close()
        await shut(gw, clients)

    run(main())


def test_disconnect_mid_transaction_keeps_the_bus_in_step(
    libmodbus_tcp: str,
    silent_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    async def main() -> None:
        gw, clients = await open_gateway([(silent_tcp, "1-10")], timeout=0.4)
        _reader, writer = await raw(gw)
        writer.write(b"".join(encode_mbap(n, 1, READ) for n in range(5)))
        await until(lambda: gw.stats()["queued"] == [4])  # the first is on the bus
        writer.close()
        await until(lambda: gw.stats()["open_connections"] == 0)
        assert gw.stats()["queued"] == [0] and gw.counters["jobs_dropped"] == 4
        # the next client's request waits for the one on the wire, then goes
        c = await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}", timeout=3.0)  # type: ignore[index]
        with pytest.raises(ExceptionResponseError) as info:
            await c.request(2, READ)
        assert info.value.code == 0x0B
        assert gw.stats()["bus_transactions"] == [2]  # one abandoned, one for c
        await c.close()
        await shut(gw, clients)

    run(main())


def test_connection_limit_and_stuck_client(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        limits = GatewayLimits(max_connections=2, max_write_buffer=4096)
        gw, clients = await open_gateway([(libmodbus_tcp, "1")], limits)
        _stuck_r, stuck_w = await raw(gw)
        ok_r, ok_w = await raw(gw)
        big = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 125)
        # the stuck client pipelines and never reads; the other one is served meanwhile
        stuck_w.write(b"".join(encode_mbap(n, 1, big) for n in range(16)))
        for n in range(50):
            ok_w.write(encode_mbap(n, 1, READ))
            assert (await read_adu(ok_r))[:2] == struct.pack(">H", n)
        assert gw.stats()["open_connections"] == 2
        ok_w.close()
        stuck_w.close()
        await shut(gw, clients)

    run(main())


def test_stuck_client_is_closed_and_others_are_served_meanwhile(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    async def main() -> None:
        limits = GatewayLimits(max_write_buffer=16384)
        gw, clients = await open_gateway([(libmodbus_tcp, "1")], limits)
        assert gw.address is not None
        ok_r, ok_w = await raw(gw)
        stuck = stuck_socket(gw.address)
        big = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 125)  # 259-byte answers
        burst = b"".join(encode_mbap(n, 1, big) for n in range(64))
        flooding = asyncio.ensure_future(flood(stuck, burst))
        served = 0
        while not flooding.done():  # the other client, one request at a time, meanwhile
            ok_w.write(encode_mbap(served & 0xFFFF, 1, READ))
            adu = parse_tcp_stream(await read_adu(ok_r), "master")[0]
            assert adu.transaction == served & 0xFFFF
            assert pdu.parse_registers(adu.pdu, 4) == pattern.holdings(1, 0, 4)
            served += 1
        await flooding
        stuck.close()
        assert gw.counters["slow_clients"] == 1 and gw.counters["bad_headers"] == 0
        # the bound held: what the gateway took before closing is the limit, its socket
        # buffer (twice the limit on Linux) and the client's window, not megabytes
        unread = (gw.counters["answers"] - served) * 259 + gw.counters["busy"] * 9
        assert 16384 < unread < 8 * 16384
        assert served > 0  # answered while the stuck client was flooding
        await until(lambda: gw.stats()["open_connections"] == 1)
        for n in range(20):  # and after
            ok_w.write(encode_mbap(n, 1, READ))
            assert (await read_adu(ok_r))[:2] == struct.pack(">H", n)
        ok_w.close()
        await shut(gw, clients)

    run(main())


@given(
    ops=st.lists(
        st.one_of(
            st.tuples(st.just("submit"), st.integers(0, 5)),
            st.tuples(st.just("pop"), st.just(0)),
            st.tuples(st.just("drop"), st.integers(0, 5)),
        ),
        max_size=200,
    )
)
@settings(max_examples=300, deadline=None)
def test_fair_queue_properties(ops: list[tuple[str, int]]) -> None:
    """Bounds hold, each connection's jobs come out in order, and no connection with
    jobs waiting is passed over more than once by each of the other connections."""
    q = FairQueue(max_per_connection=4, max_total=12)
    model: dict[int, list[int]] = {}
    waits: dict[int, int] = {}
    serial = 0
    for op, conn in ops:
        if op == "submit":
            serial += 1
            full = len(q) >= 12 or len(model.get(conn, [])) >= 4
            try:
                q.submit(Job(conn=conn, transaction=serial, unit=1, slave=1, pdu=READ))
            except QueueFull:
                assert full
            else:
                assert not full
                model.setdefault(conn, []).append(serial)
        elif op == "drop":
            assert q.drop(conn) == len(model.pop(conn, []))
            waits.pop(conn, None)
        else:
            j = q.pop()
            if not any(model.values()):
                assert j is None
                continue
            assert j is not None and model[j.conn][0] == j.transaction  # FIFO per connection
            model[j.conn].pop(0)
            active = [c for c, jobs in model.items() if jobs or c == j.conn]
            for c in active:
                waits[c] = 0 if c == j.conn else waits.get(c, 0) + 1
                assert waits[c] <= 5  # at most one turn of each of the other connections
            if not model[j.conn]:
                del model[j.conn]
                waits.pop(j.conn, None)
        assert len(q) == sum(len(v) for v in model.values()) <= 12


def test_rtu_over_tcp_listener(libmodbus_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient

    from pyrtu import add_crc
    from pyrtu.drivers.aio import AsyncMaster

    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1-5")])
        await gw.close()  # again, with the RTU listener
        gw = Gateway([(clients[0], parse_units("1-5"))])
        await gw.start("127.0.0.1", 0, rtu=("127.0.0.1", 0))
        assert gw.rtu_address is not None
        host, port = gw.rtu_address
        async with AsyncMaster(f"rtu+tcp://{host}:{port}", timeout=2.0) as m:
            assert await m.read_holding_registers(1, 3, 4) == pattern.holdings(1, 3, 4)
            with pytest.raises(ExceptionResponseError) as info:
                await m.read_holding_registers(9, 0, 1)  # no bus for 9: 0x0A, an RTU frame
            assert info.value.code == 0x0A

        def pymodbus_rtu() -> list[int]:
            client = ModbusTcpClient(host, port=port, framer=FramerType.RTU, timeout=2, retries=0)
            assert client.connect()
            try:
                return list(client.read_input_registers(2, count=3, device_id=2).registers)
            finally:
                client.close()

        assert await asyncio.to_thread(pymodbus_rtu) == pattern.inputs(1, 2, 3)
        # noise before a frame is skipped (RTU resynchronises by CRC), not a reason to close
        reader, writer = await asyncio.open_connection(host, port)
        writer.write(b"\xff\x00\x13" + add_crc(bytes.fromhex("0103000a0002")))
        answer = await asyncio.wait_for(reader.readexactly(9), 3.0)
        assert answer == add_crc(
            bytes.fromhex("010304")
            + bytes.fromhex("".join(f"{v:04x}" for v in pattern.holdings(1, 10, 2)))
        )
        assert gw.counters["rtu_discarded_bytes"] == 3
        writer.close()
        await shut(gw, clients)

    run(main())


def test_bus_queue_limit_answers_busy_to_any_connection(silent_tcp: str, run) -> None:  # type: ignore[no-untyped-def]
    """max_queued_per_bus bounds the bus's queue across connections: once the bus has
    that many waiting, a request from another connection is answered 0x06 at once."""

    async def main() -> None:
        limits = GatewayLimits(max_queued_per_connection=8, max_queued_per_bus=3)
        gw, clients = await open_gateway([(silent_tcp, "1")], limits, timeout=0.5)
        first_r, first_w = await raw(gw)
        first_w.write(encode_mbap(0, 1, READ))
        await until(lambda: gw.stats()["requests"] == 1 and gw.stats()["queued"] == [0])
        first_w.write(b"".join(encode_mbap(n, 1, READ) for n in range(1, 4)))  # 3 waiting
        await until(lambda: gw.stats()["queued"] == [3])
        other_r, other_w = await raw(gw)
        other_w.write(encode_mbap(0x4242, 1, READ))
        busy = parse_tcp_stream(await read_adu(other_r), "master")[0]
        assert (busy.transaction, busy.function, busy.exception_code) == (0x4242, 0x83, 6)
        assert gw.counters["busy"] == 1
        # the first connection's four go on to time out on the dead bus, in order
        later = [parse_tcp_stream(await read_adu(first_r, 5.0), "master")[0] for _ in range(4)]
        assert [(f.transaction, f.exception_code) for f in later] == [(n, 11) for n in range(4)]
        for w in (first_w, other_w):
            w.close()
        await shut(gw, clients)

    run(main())


def test_a_bus_whose_port_failed_answers_0x0a_and_the_other_goes_on(
    peer_binaries: PeerBinaries,
    libmodbus_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    """A bus whose connection (port) is gone answers 0x0A, gateway path unavailable, at
    once; the other bus behind the same listener is not affected."""
    port = free_tcp_port()
    doomed = libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 2).start()

    async def main() -> None:
        gw, clients = await open_gateway([(libmodbus_tcp, "1"), (f"tcp://127.0.0.1:{port}", "2")])
        assert gw.address is not None
        c = await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}", timeout=5.0)
        got = await c.request(2, READ)
        assert pdu.parse_registers(got or b"", 4) == pattern.holdings(2, 0, 4)
        doomed.stop()  # the server behind bus 1 exits: its connection closes
        for _ in range(3):
            with pytest.raises(ExceptionResponseError) as info:
                await c.request(2, READ)
            assert info.value.code == 0x0A
            got = await c.request(1, READ)
            assert pdu.parse_registers(got or b"", 4) == pattern.holdings(1, 0, 4)
        assert gw.counters["timeouts"] == 0
        # counted as what it is (not "no route"), one outage reported, the bus down
        assert (gw.counters["bus_unavailable"], gw.counters["no_route"]) == (3, 0)
        assert gw.counters["bus_failures"] == 1 and gw.stats()["bus_down"] == [False, True]
        await c.close()
        await shut(gw, clients)

    try:
        run(main())
    finally:
        doomed.stop()


class FaultyBus:
    """A bus of the Python API (any object with ``async request``) with a bug: it
    raises KeyError for slave 7 and for a broadcast of FC 05, and answers the others
    from the register pattern."""

    async def request(self, slave: int, request: bytes) -> bytes | None:
        if slave == 7 or (slave == 0 and request[0] == 5):
            raise KeyError("a bug in the bus")
        if slave == 0:
            return None
        count = int.from_bytes(request[3:5], "big")
        values = pattern.holdings(slave, int.from_bytes(request[1:3], "big"), count)
        return bytes((3, 2 * count)) + b"".join(v.to_bytes(2, "big") for v in values)


def test_a_bus_that_raises_gets_0x0b_and_its_worker_goes_on(
    run,  # type: ignore[no-untyped-def]
    caplog: pytest.LogCaptureFixture,
) -> None:
    async def main() -> None:
        gw = Gateway([(FaultyBus(), range(1, 10))])
        await gw.start("127.0.0.1", 0)
        assert gw.address is not None
        c = await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}", timeout=5.0)
        for _ in range(2):
            with pytest.raises(ExceptionResponseError) as info:
                await c.request(7, READ)
            assert info.value.code == 0x0B
            got = await c.request(1, READ)  # the same bus, served after the failure
            assert pdu.parse_registers(got or b"", 4) == pattern.holdings(1, 0, 4)
        assert gw.counters["timeouts"] == 2 and gw.stats()["bus_transactions"] == [4]
        # a broadcast the bus fails on is still not answered (no frame for unit 0)
        assert await c.request(0, pdu.write_coil_request(3, True)) is None
        got = await c.request(2, READ)
        assert pdu.parse_registers(got or b"", 4) == pattern.holdings(2, 0, 4)
        assert c.counters["late"] == 0 and gw.stats()["bus_transactions"] == [6]
        await c.close()
        await gw.close()

    with caplog.at_level("ERROR", logger="pyrtu.gateway"):
        run(main())
    assert [r.exc_info[0] for r in caplog.records if r.exc_info] == [KeyError] * 3
