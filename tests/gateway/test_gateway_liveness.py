"""Clients that do not talk cannot hold the gateway: the header and idle timeouts
and eviction from a full connection table (pyrtu.gateway._live), with real sockets
and a libmodbus TCP server as the bus."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import pytest
from peers import pattern

from pyrtu import encode_mbap, pdu
from pyrtu.gateway import Gateway, GatewayLimits, parse_units
from pyrtu.gateway._live import HEADER, IDLE, Liveness, pick_victim
from pyrtu.tcp import AsyncTcpClient

pytest_plugins = ["peers.fixtures"]

READ = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 4)
REQUEST = encode_mbap(1, 1, READ)  # 12 bytes


# -- sans-I/O ------------------------------------------------------------------------


def test_liveness_header_and_idle_timeouts() -> None:
    live = Liveness(connected=100.0)
    assert live.expired(104.9, 5.0, 120.0) is None
    live.data(101.0, partial=True, completed=False)  # 3 bytes of a header
    live.data(104.0, partial=True, completed=False)  # more: the clock keeps running
    assert live.expired(105.9, 5.0, 120.0) is None
    assert live.expired(106.0, 5.0, 120.0) == HEADER
    assert live.expired(1e6, 0, 0) is None  # 0: no limit
    live.data(106.5, partial=False, completed=True)  # the request is complete
    assert live.partial_since is None and live.last_active == 106.5
    live.outstanding += 1  # queued for a bus: never idle meanwhile
    assert live.expired(500.0, 5.0, 120.0) is None
    live.answered(501.0)
    assert live.expired(620.9, 5.0, 120.0) is None
    assert live.expired(621.0, 5.0, 120.0) == IDLE
    # a chunk that ends one request and begins the next starts the next one's clock
    live.data(700.0, partial=True, completed=True)
    assert live.partial_since == 700.0
    never = Liveness(connected=0.0)
    assert never.expired(119.0, 5.0, 120.0) is None and never.expired(120.0, 5.0, 120.0) == IDLE


def test_pick_victim_prefers_the_silent_and_spares_work_in_progress() -> None:
    talked = Liveness(connected=0.0, last_active=50.0)
    idle_longer = Liveness(connected=0.0, last_active=10.0)
    silent_old = Liveness(connected=5.0)
    silent_new = Liveness(connected=60.0)
    busy = Liveness(connected=0.0, outstanding=2)
    assert pick_victim([(1, talked, False), (2, silent_new, False), (3, silent_old, False)]) == 3
    assert pick_victim([(1, talked, False), (2, idle_longer, False)]) == 2
    assert pick_victim([(1, busy, False), (2, talked, True)]) is None  # unsent answers
    assert pick_victim([]) is None


def test_limits_validate_the_timeouts() -> None:
    for name in ("header_timeout", "idle_timeout"):
        for bad in (-1, float("nan"), float("inf")):
            with pytest.raises(ValueError, match=name):
                GatewayLimits(**{name: bad})
        with pytest.raises(TypeError, match=name):
            GatewayLimits(**{name: "5"})
    with pytest.raises(TypeError, match="backoff"):
        GatewayLimits(backoff=1.0)  # type: ignore[arg-type]
    limits = GatewayLimits()
    assert (limits.header_timeout, limits.idle_timeout) == (5.0, 120.0)


# -- with sockets --------------------------------------------------------------------


async def until(check: object, timeout: float = 20.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not check():  # type: ignore[operator]
        assert loop.time() < end, "the gateway did not get there"
        await asyncio.sleep(0.01)


async def served(gw: Gateway, timeout: float = 5.0) -> list[int]:
    """A well-behaved client: connect, one request, its answer."""
    assert gw.address is not None
    url = f"tcp://{gw.address[0]}:{gw.address[1]}"
    async with await AsyncTcpClient.connect(url, timeout=timeout) as c:
        return pdu.parse_registers(await c.request(1, READ) or b"", 4)


async def drip(writer: asyncio.StreamWriter, period: float = 1.0) -> None:
    """One byte of a request per ``period`` (1 byte/s), for ever (until cancelled or
    the gateway closes the connection)."""
    while True:
        for b in REQUEST:
            writer.write(bytes((b,)))
            await asyncio.sleep(period)


class Silent:
    """64 clients that hold slots without talking: a third send nothing, a third
    drip a request one byte a second, a third send 3 bytes of a header and stop."""

    def __init__(self) -> None:
        self.streams: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []
        self.tasks: list[asyncio.Task[None]] = []

    async def open(self, gw: Gateway, n: int) -> None:
        assert gw.address is not None
        for i in range(n):
            r, w = await asyncio.open_connection(*gw.address)
            self.streams.append((r, w))
            if i % 3 == 1:
                self.tasks.append(asyncio.ensure_future(drip(w)))
            elif i % 3 == 2:
                w.write(REQUEST[:3])

    async def close(self) -> None:
        for t in self.tasks:
            t.cancel()
        for _, w in self.streams:
            w.close()
        await asyncio.sleep(0)


@pytest.fixture
def run() -> Iterator[object]:
    loop = asyncio.new_event_loop()
    yield loop.run_until_complete
    loop.close()


def test_a_full_table_of_silent_clients_gives_way_to_one_that_talks(
    libmodbus_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    """64 idle / slow-drip / half-header clients fill --max-connections (the
    default); the timeouts are set long, so only eviction can let a newcomer in.
    Each well-behaved client is served, and a silent one gives way to it."""

    async def main() -> None:
        bus = await AsyncTcpClient.connect(libmodbus_tcp, timeout=2.0, max_in_flight=1)
        limits = GatewayLimits(header_timeout=600.0, idle_timeout=600.0)
        gw = await Gateway([(bus, parse_units("1-5"))], limits).start("127.0.0.1", 0)
        full = limits.max_connections
        silent = Silent()
        for k in range(5):
            await silent.open(gw, full - gw.stats()["open_connections"])  # (top up)
            await until(lambda: gw.stats()["open_connections"] == full)
            assert await served(gw) == pattern.holdings(1, 0, 4)
            assert gw.counters["evicted"] == k + 1
            await until(lambda: gw.stats()["open_connections"] == full - 1)  # it left
        assert gw.counters["refused"] == 0
        await until(lambda: sum(r.at_eof() for r, _ in silent.streams) == 5)
        assert gw.counters["header_timeouts"] == gw.counters["idle_timeouts"] == 0
        await silent.close()
        await gw.close()
        await bus.close()

    run(main())


def test_a_client_that_talks_keeps_its_slot_while_silent_ones_come_and_go(
    libmodbus_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    async def main() -> None:
        bus = await AsyncTcpClient.connect(libmodbus_tcp, timeout=2.0, max_in_flight=1)
        limits = GatewayLimits(max_connections=8, header_timeout=600.0, idle_timeout=600.0)
        gw = await Gateway([(bus, parse_units("1"))], limits).start("127.0.0.1", 0)
        assert gw.address is not None
        url = f"tcp://{gw.address[0]}:{gw.address[1]}"
        keeper = await AsyncTcpClient.connect(url, timeout=5.0)
        assert pdu.parse_registers(await keeper.request(1, READ) or b"", 4) == (
            pattern.holdings(1, 0, 4)
        )
        silent = Silent()
        await silent.open(gw, 30)  # 7 slots, 30 newcomers: 23 evictions, all silent ones
        await until(lambda: gw.counters["evicted"] == 23)
        assert gw.stats()["open_connections"] == 8
        for _ in range(3):  # the client that talked was never the one to go
            got = await keeper.request(1, READ)
            assert pdu.parse_registers(got or b"", 4) == pattern.holdings(1, 0, 4)
        await keeper.close()
        await silent.close()
        await gw.close()
        await bus.close()

    run(main())


def test_a_full_table_of_clients_with_work_in_progress_refuses_the_newcomer(
    silent_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    async def main() -> None:
        bus = await AsyncTcpClient.connect(silent_tcp, timeout=30.0, max_in_flight=1)
        limits = GatewayLimits(max_connections=2)
        gw = await Gateway([(bus, parse_units("1"))], limits).start("127.0.0.1", 0)
        assert gw.address is not None
        writers = []
        for n in range(2):
            _, w = await asyncio.open_connection(*gw.address)
            w.write(encode_mbap(n, 1, READ))  # waits for the dead device
            writers.append(w)
        await until(lambda: gw.counters["requests"] == 2)
        third_r, third_w = await asyncio.open_connection(*gw.address)
        assert await asyncio.wait_for(third_r.read(), 5.0) == b""  # refused
        assert gw.counters["refused"] == 1 and gw.counters["evicted"] == 0
        for w in (*writers, third_w):
            w.close()
        await gw.close()
        await bus.close()

    run(main())


@pytest.mark.wall_clock
def test_header_and_idle_timeouts_close_the_silent_and_spare_the_talkers(
    libmodbus_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    """header_timeout 2.5 s (a 12-byte request dripped at 1 byte/s takes 11 s),
    idle_timeout 4 s (a silent Modbus TCP client, and one on the RTU listener).
    Bounds: each is closed after its timeout (not before) and within 10 s more (the
    sweep runs every timeout/4 s); a client polling every 0.5 s is never closed and
    is served throughout."""

    async def main() -> None:
        bus = await AsyncTcpClient.connect(libmodbus_tcp, timeout=2.0, max_in_flight=1)
        limits = GatewayLimits(header_timeout=2.5, idle_timeout=4.0)
        gw = Gateway([(bus, parse_units("1"))], limits)
        await gw.start("127.0.0.1", 0, rtu=("127.0.0.1", 0))
        assert gw.address is not None and gw.rtu_address is not None
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        silent = Silent()
        await silent.open(gw, 3)  # idle, drip, half header
        silent.streams.append(await asyncio.open_connection(*gw.rtu_address))  # RTU, idle
        url = f"tcp://{gw.address[0]}:{gw.address[1]}"
        poller = await AsyncTcpClient.connect(url, timeout=5.0)

        async def closed_at(reader: asyncio.StreamReader) -> float:
            try:
                await asyncio.wait_for(reader.read(), 30.0)
            except ConnectionResetError:
                pass
            return loop.time() - t0

        waits = [asyncio.ensure_future(closed_at(r)) for r, _ in silent.streams]
        polls = 0
        while not all(w.done() for w in waits):
            got = await poller.request(1, READ)
            assert pdu.parse_registers(got or b"", 4) == pattern.holdings(1, 0, 4)
            polls += 1
            await asyncio.sleep(0.5)
        idle_at, drip_at, half_at, rtu_at = (w.result() for w in waits)
        assert limits.idle_timeout <= idle_at < limits.idle_timeout + 10.0
        assert limits.idle_timeout <= rtu_at < limits.idle_timeout + 10.0
        assert limits.header_timeout <= drip_at < limits.header_timeout + 10.0
        assert limits.header_timeout <= half_at < limits.header_timeout + 10.0
        assert gw.counters["header_timeouts"] == 2 and gw.counters["idle_timeouts"] == 2
        assert polls > 4 and gw.stats()["open_connections"] == 1  # the poller
        await poller.close()
        await silent.close()
        await gw.close()
        await bus.close()

    run(main())


@pytest.mark.wall_clock
def test_rtu_listener_closes_a_partial_request_at_the_header_timeout(
    libmodbus_tcp: str,
    run,  # type: ignore[no-untyped-def]
) -> None:
    """The RTU-over-TCP listener times out a request that never completes, as the MBAP
    listener does: a client that sends 3 bytes of an RTU request and stops, and one
    that drips a request a byte every 0.4 s (8 bytes: 2.8 s), are closed after the
    header timeout (1 s; the idle timeout is 600 s, so only the header timeout can
    close them) and within 5 s more (the sweep runs every 0.25 s); an RTU client that
    sends whole requests is served throughout and kept."""
    from pyrtu import add_crc

    rtu_read = add_crc(b"\x01" + READ)  # 8 bytes

    async def main() -> None:
        bus = await AsyncTcpClient.connect(libmodbus_tcp, timeout=2.0, max_in_flight=1)
        limits = GatewayLimits(header_timeout=1.0, idle_timeout=600.0)
        gw = Gateway([(bus, parse_units("1"))], limits)
        await gw.start("127.0.0.1", 0, rtu=("127.0.0.1", 0))
        assert gw.rtu_address is not None
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        half_r, half_w = await asyncio.open_connection(*gw.rtu_address)
        half_w.write(rtu_read[:3])
        drip_r, drip_w = await asyncio.open_connection(*gw.rtu_address)

        async def dripping() -> None:
            while True:
                for b in rtu_read:
                    drip_w.write(bytes((b,)))
                    await asyncio.sleep(0.4)

        dripper = asyncio.ensure_future(dripping())
        talker_r, talker_w = await asyncio.open_connection(*gw.rtu_address)

        async def closed_at(reader: asyncio.StreamReader) -> float:
            try:
                await asyncio.wait_for(reader.read(), 15.0)
            except ConnectionResetError:
                pass
            return loop.time() - t0

        waits = [asyncio.ensure_future(closed_at(r)) for r in (half_r, drip_r)]
        served = 0
        while not all(w.done() for w in waits):
            talker_w.write(rtu_read)
            answer = await asyncio.wait_for(talker_r.readexactly(5 + 8), 5.0)
            assert answer == add_crc(b"\x01\x03\x08" + pdu_words(pattern.holdings(1, 0, 4)))
            served += 1
            await asyncio.sleep(0.2)
        half_at, drip_at = (w.result() for w in waits)
        assert limits.header_timeout <= half_at < limits.header_timeout + 5.0
        assert limits.header_timeout <= drip_at < limits.header_timeout + 5.0
        assert gw.counters["header_timeouts"] == 2 and gw.counters["idle_timeouts"] == 0
        assert served >= 4 and gw.stats()["open_connections"] == 1  # the talker
        dripper.cancel()
        for w in (half_w, drip_w, talker_w):
            w.close()
        await gw.close()
        await bus.close()

    run(main())


def pdu_words(values: list[int]) -> bytes:
    return b"".join(v.to_bytes(2, "big") for v in values)
