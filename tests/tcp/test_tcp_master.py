"""``Master("tcp://...")`` and ``AsyncMaster("tcp://...")`` (Modbus TCP), and the
``rtu+tcp://`` masters, against real servers on 127.0.0.1: pymodbus's and libmodbus's
TCP servers, and socat joining TCP to a pty with a pyrtu slave (RTU over TCP)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from peers import pattern
from peers.tools import (
    free_tcp_port,
    pyrtu_slave_process,
    socat_pty_over_tcp,
)

from pyrtu import ExceptionResponseError, Master, NoResponseError, PortError
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncMaster

pytest_plugins = ["peers.fixtures"]


def test_master_over_modbus_tcp(tcp_server: tuple[str, int]) -> None:
    url, _ = tcp_server
    with Master(url, timeout=2.0) as m:
        assert type(m) is Master and m.mode == "tcp"  # one class, a TCP link
        assert m.read_holding_registers(1, 0, 10) == pattern.holdings(1, 0, 10)
        assert m.read_input_registers(1, 3, 4) == pattern.inputs(1, 3, 4)
        assert m.read_coils(1, 0, 30) == pattern.coils(1, 0, 30)
        assert m.read_discrete_inputs(1, 7, 9) == pattern.discretes(1, 7, 9)
        m.write_register(1, 10, 555)
        m.write_registers(1, 20, [1, 2, 3])
        m.write_coil(1, 4, True)
        m.write_coils(1, 40, [True, False, True])
        assert m.read_holding_registers(1, 10, 1) == [555]
        assert m.read_holding_registers(1, 20, 3) == [1, 2, 3]
        assert m.read_coils(1, 40, 3) == [True, False, True]
        assert m.read_write_registers(1, 20, 2, 30, [9, 8]) == [1, 2]
        with pytest.raises(ExceptionResponseError) as info:
            m.read_holding_registers(1, 60000, 5)
        assert info.value.code == 2
        with pytest.raises(ValueError, match="count"):
            m.read_holding_registers(1, 0, 0)  # checked before anything is sent
        assert m.counters["responses"] == 12 and m.counters["exceptions"] == 1
        assert "Modbus TCP" in repr(m)


def test_async_master_over_modbus_tcp(tcp_server: tuple[str, int]) -> None:
    url, window = tcp_server

    async def main() -> None:
        async with AsyncMaster(url, timeout=2.0, max_in_flight=window) as m:
            reads = [m.read_holding_registers(1, i, 3) for i in range(30)]
            assert await asyncio.gather(*reads) == [pattern.holdings(1, i, 3) for i in range(30)]
            await m.write_register(1, 11, 1234)
            assert await m.read_holding_registers(1, 11, 1) == [1234]
            with pytest.raises(ExceptionResponseError):
                await m.read_input_registers(1, 60000, 1)

    asyncio.run(main())


def test_bad_urls_and_dead_servers() -> None:
    with pytest.raises(ValueError, match="tcp://"):
        Master("tcp://host:notaport")
    with pytest.raises(PortError, match="cannot connect"):
        Master(f"tcp://127.0.0.1:{free_tcp_port()}", timeout=1.0)
    with pytest.raises(ValueError, match="timeout"):
        Master("tcp://127.0.0.1:1", timeout=0)

    async def main() -> None:
        m = AsyncMaster(f"tcp://127.0.0.1:{free_tcp_port()}", timeout=1.0)
        with pytest.raises(PortError, match="cannot connect"):
            await m.read_coils(1, 0, 1)

    asyncio.run(main())


def test_retries_and_timeout_on_a_silent_server() -> None:
    import socket

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    url = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    try:
        with Master(url, timeout=0.1, retries=2) as m:
            with pytest.raises(NoResponseError):
                m.read_holding_registers(1, 0, 1)
            assert m.counters["timeouts"] == 3 and m.counters["requests"] == 3
            m.timeout = 0.05
            assert m.timeout == 0.05
    finally:
        listener.close()


@pytest.fixture
def rtu_device_server(tmp_path: Path) -> Iterator[str]:
    """A pyrtu slave (address 4) behind socat: rtu+tcp:// URL."""
    link = tmp_path / "serial"
    with socat_pty_over_tcp(link) as port, pyrtu_slave_process(str(link), 4, t35=0):
        yield f"rtu+tcp://127.0.0.1:{port}"


def test_masters_over_rtu_tcp(rtu_device_server: str) -> None:
    with Master(rtu_device_server, timeout=1.0) as m:
        assert type(m) is Master and m.mode == "rtu" and m.t35 == 0
        assert m.read_holding_registers(4, 5, 5) == pattern.holdings(4, 5, 5)
        m.write_register(4, 8, 99)
        assert m.read_holding_registers(4, 8, 1) == [99]
        assert m.counters["crc_errors"] == 0


def test_rtu_tcp_master_with_a_line(rtu_device_server: str) -> None:
    """``line=`` on rtu+tcp://: the socket has no wire timing, so t3.5 is 0 unless the
    line sets it (``line=`` was refused as "not both" with the implied t35=0)."""
    with Master(rtu_device_server, line=LineConfig(baudrate=9600), timeout=1.0) as m:
        assert m.t35 == 0 and m.line.baudrate == 9600
        assert m.read_holding_registers(4, 5, 2) == pattern.holdings(4, 5, 2)


def test_async_master_over_rtu_tcp(rtu_device_server: str) -> None:
    async def main() -> None:
        async with AsyncMaster(rtu_device_server, timeout=1.0) as m:
            got = await asyncio.gather(*(m.read_input_registers(4, i, 2) for i in range(10)))
            assert got == [pattern.inputs(4, i, 2) for i in range(10)]

    asyncio.run(main())


def _serial_attributes(m: Master | AsyncMaster, url: str) -> None:
    """What a TCP master answers in place of a serial line's properties."""
    with pytest.raises(AttributeError, match="no serial line") as info:
        _ = m.line
    assert url in str(info.value)
    assert not hasattr(m, "line") and getattr(m, "line", None) is None
    assert not hasattr(m, "port")
    assert (m.mode, m.t35, m.echo, m.broadcast_delay) == ("tcp", 0.0, False, 0.0)
    assert m.url == url  # type: ignore[union-attr]


def test_tcp_master_in_place_of_a_serial_one(tcp_server: tuple[str, int]) -> None:
    """`Master`'s serial-line properties on a TCP master: a value where TCP has one, a
    clear AttributeError for the line itself; last_answer_time stamps each answer."""
    url, _ = tcp_server
    with Master(url, timeout=2.0) as m:
        _serial_attributes(m, url)
        assert m.last_answer_time is None
        before = time.monotonic()
        assert m.read_holding_registers(1, 0, 2) == pattern.holdings(1, 0, 2)
        first = m.last_answer_time
        assert first is not None and before <= first <= time.monotonic()
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(1, 60000, 1)
        assert m.last_answer_time is not None and m.last_answer_time >= first  # an answer too

    async def main() -> None:
        async with AsyncMaster(url, timeout=2.0) as am:
            _serial_attributes(am, url)
            assert am.last_answer_time is None  # not even connected yet
            before = time.monotonic()
            assert await am.read_input_registers(1, 3, 2) == pattern.inputs(1, 3, 2)
            stamp = am.last_answer_time
            assert stamp is not None and before <= stamp <= time.monotonic()

    asyncio.run(main())


def test_poller_over_modbus_tcp() -> None:
    """A `pyrtu.Poller` bus on tcp:// (the AsyncMaster the poller opens is the TCP one,
    whose last_answer_time stamps the values), against pyrtu's TCP server."""
    import pyrtu
    from pyrtu.poller import Bus, Point
    from pyrtu.tcp.server import TcpServer

    async def main() -> None:
        store = pyrtu.DataStore()
        store.holding_registers.add_range(0, [100 + i for i in range(20)])
        async with await TcpServer.for_store(3, store).start("127.0.0.1", 0) as server:
            assert server.address is not None
            host, port = server.address
            bus = Bus("plant", f"tcp://{host}:{port}", {"timeout": 1.0})
            points = [
                Point("a", "plant", 3, "holding", 2, interval=0.02),
                Point("b", "plant", 3, "holding", 7, interval=0.02),
            ]
            got: dict[str, object] = {}

            async def watch(poller: pyrtu.Poller) -> None:
                async for update in poller.updates():
                    got[update.name] = update.value
                    if len(got) == 2:
                        break
                assert got == {"a": 102, "b": 107}
                store.holding_registers.set(7, 555)  # a later poll sees it
                async for update in poller.updates():
                    if update.name == "b" and update.value == 555:
                        break

            async with pyrtu.Poller(buses=[bus], points=points) as poller:
                # (a bound on a hang, not a timing: the updates come every 20 ms)
                await asyncio.wait_for(watch(poller), 30.0)

    asyncio.run(main())


@pytest.fixture
def pyrtu_tcp_server() -> Iterator[str]:
    """pyrtu's TcpServer for slave 4 (the pattern), in a thread's event loop."""
    import threading

    from pyrtu.tcp.server import TcpServer

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = TcpServer.for_store(4, pattern.pattern_store(4))
    asyncio.run_coroutine_threadsafe(server.start("127.0.0.1", 0), loop).result(10)
    assert server.address is not None
    try:
        yield f"tcp://127.0.0.1:{server.address[1]}"
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


def every_method(m: Master, unit: int) -> dict[str, object]:
    """Each `Master` method once, to ``unit``: what it returned, or the device's
    exception code (the request reached it and was answered)."""
    from pyrtu import pdu

    calls = {
        "read_coils": lambda: m.read_coils(unit, 0, 5),
        "read_discrete_inputs": lambda: m.read_discrete_inputs(unit, 3, 4),
        "read_holding_registers": lambda: m.read_holding_registers(unit, 7, 3),
        "read_input_registers": lambda: m.read_input_registers(unit, 2, 2),
        "write_coil": lambda: m.write_coil(unit, 40, True),
        "write_register": lambda: m.write_register(unit, 41, unit + 1000),
        "write_coils": lambda: m.write_coils(unit, 42, [True, False]),
        "write_registers": lambda: m.write_registers(unit, 43, [1, 2]),
        "mask_write_register": lambda: m.mask_write_register(unit, 43, 0x00FF, 0x0100),
        "read_write_registers": lambda: m.read_write_registers(unit, 41, 1, 50, [9]),
        "read_exception_status": lambda: m.read_exception_status(unit),
        "diagnostics": lambda: m.diagnostics(unit, 0, 0x1234),
        "get_comm_event_counter": lambda: m.get_comm_event_counter(unit),
        "get_comm_event_log": lambda: m.get_comm_event_log(unit),
        "report_server_id": lambda: m.report_server_id(unit),
        "read_fifo_queue": lambda: m.read_fifo_queue(unit, 0),
        "read_file_record": lambda: m.read_file_record(unit, [(1, 0, 1)]),
        "write_file_record": lambda: m.write_file_record(unit, [(1, 0, [5])]),
        "read_device_identification": lambda: m.read_device_identification(unit),
        "request": lambda: m.request(unit, pdu.read_request(3, 7, 1)),
        "execute": lambda: m.execute(unit, 3, bytes.fromhex("00070001")),
    }
    out: dict[str, object] = {}
    for name, call in calls.items():
        try:
            out[name] = call()
        except ExceptionResponseError as exc:
            out[name] = ("exception", exc.code)
    return out


def test_unit_0xff_and_0_in_every_method(pyrtu_tcp_server: str) -> None:
    """Messaging on TCP/IP Implementation Guide 4.4.1.2: 0xFF addresses the TCP device
    (libmodbus's default), and so does 0.  Every method takes 0xFF (a serial
    master's check refused it: "slave must be 0..247"), reads take 0 and await the
    answer, writes to 0 stay broadcasts; 256 is still refused before a byte is sent."""
    with Master(pyrtu_tcp_server, timeout=2.0) as m:
        direct = every_method(m, 4)
        via_ff = every_method(m, 0xFF)
        # the same answers, but for what the first round changed: the register the
        # writes set (unit + 1000) and the device's event counters
        assert via_ff["read_write_registers"] == [0xFF + 1000]
        assert via_ff["get_comm_event_counter"][1] > direct["get_comm_event_counter"][1]  # type: ignore[index]
        stateful = ("read_write_registers", "get_comm_event_counter", "get_comm_event_log")
        assert {k: v for k, v in via_ff.items() if k not in stateful} == {
            k: v for k, v in direct.items() if k not in stateful
        }
        assert direct["read_holding_registers"] == pattern.holdings(4, 7, 3)
        assert m.read_holding_registers(0xFF, 7, 3) == pattern.holdings(4, 7, 3)
        assert m.read_holding_registers(0, 7, 3) == pattern.holdings(4, 7, 3)  # answered
        assert m.read_input_registers(0, 2, 2) == pattern.inputs(4, 2, 2)
        assert m.report_server_id(0) == direct["report_server_id"]
        assert m.write_register(0, 60, 606) is None  # a broadcast: no answer awaited
        assert m.counters["broadcasts"] == 1
        for bad, error in ((256, ValueError), (-1, ValueError), ("1", TypeError)):
            with pytest.raises(error, match="slave"):
                m.read_holding_registers(bad, 0, 1)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="count"):  # the other checks still run
            m.read_holding_registers(0xFF, 0, 0)
        sent = m.counters["requests"]
        with pytest.raises(ValueError, match="slave"):
            m.write_register(300, 0, 1)
        assert m.counters["requests"] == sent  # nothing was sent


def test_async_unit_0xff_and_0_concurrently(pyrtu_tcp_server: str) -> None:
    """The unit each await was given, even with several on the wire at once."""

    async def main() -> None:
        async with AsyncMaster(pyrtu_tcp_server, timeout=2.0, max_in_flight=4) as m:
            got = await asyncio.gather(
                *(m.read_holding_registers(unit, 10 * k, 2)
                  for k, unit in enumerate([0xFF, 4, 0, 0xFF, 4, 0]))
            )  # fmt: skip
            assert got == [pattern.holdings(4, 10 * k, 2) for k in range(6)]
            await m.write_registers(0xFF, 70, [1, 2, 3])
            assert await m.read_holding_registers(0, 70, 3) == [1, 2, 3]
            assert await m.request(0xFF, bytes.fromhex("0300460001")) == bytes.fromhex("03020001")
            with pytest.raises(ValueError, match="slave"):
                await m.read_coils(256, 0, 1)

    asyncio.run(main())
