"""A TCP master whose connection broke reconnects at its next request: the server
restarted on the same port (a real pyrtu `TcpServer`, stopped and started again), the
connection shut, the server away for a while (the back-off of
`pyrtu.drivers.reconnect`); the counters go on; a closed master stays closed.  The
sync client on both backends (its transaction in C or in the twin)."""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Iterator
from types import ModuleType

import pytest
from peers.tools import free_tcp_port

from pyrtu import DataStore, Master, PortError
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.reconnect import Backoff, Reconnect
from pyrtu.pdu.errors import ExceptionResponseError
from pyrtu.tcp import AsyncTcpClient, TcpClient
from pyrtu.tcp.protocol import TcpClientProtocol
from pyrtu.tcp.server import TcpServer

#: a read of holding register 0 (function 3, address 0, count 1)
READ_0 = bytes((3, 0, 0, 0, 1))


class Restartable:
    """A pyrtu `TcpServer` over one DataStore on a fixed port, on the test's event
    loop thread, that can be stopped and started again."""

    def __init__(self, loop: asyncio.AbstractEventLoop, port: int) -> None:
        self.loop, self.port = loop, port
        self.store = DataStore()
        self.store.holding_registers.add_range(0, [1000 + i for i in range(10)])
        self.server: TcpServer | None = None

    def start(self) -> None:
        self.server = TcpServer.for_store(1, self.store)
        coro = self.server.start("127.0.0.1", self.port)
        asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def stop(self) -> None:
        assert self.server is not None
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(10)
        self.server = None


async def until_broken(client: AsyncTcpClient | None, within: float = 10.0) -> None:
    """Wait (at most ``within`` seconds) until the event loop has heard the
    connection end."""
    assert client is not None
    deadline = time.monotonic() + within
    while not client.broken:
        assert time.monotonic() < deadline, "the connection's end was never heard"
        await asyncio.sleep(0.01)


@pytest.fixture
def server(loop: asyncio.AbstractEventLoop) -> Iterator[Restartable]:
    srv = Restartable(loop, free_tcp_port())
    srv.start()
    yield srv
    if srv.server is not None:
        srv.stop()


def test_the_sync_master_reconnects_after_the_server_restarted(
    server: Restartable, backend: ModuleType
) -> None:
    with Master(f"tcp://127.0.0.1:{server.port}", timeout=2.0, backend=backend.BACKEND) as m:
        assert m.read_holding_registers(1, 0, 2) == [1000, 1001]
        server.stop()
        server.start()
        # the request that finds the old connection closed fails (it may have been
        # sent: it is not sent again); the next one runs on a new connection
        with pytest.raises(PortError, match=r"closed the connection|send failed|receive failed"):
            m.read_holding_registers(1, 0, 2)
        assert m.read_holding_registers(1, 2, 2) == [1002, 1003]
        server.store.holding_registers.set(4, 7)
        m.write_register(1, 5, 8)
        assert m.read_holding_registers(1, 4, 2) == [7, 8]
        # the counters go on across the connections: 5 requests, 4 answered
        assert m.counters["requests"] == 5 and m.counters["responses"] == 4


def test_a_request_between_attempts_fails_at_once_naming_the_next_attempt(
    server: Restartable, backend: ModuleType, caplog: pytest.LogCaptureFixture
) -> None:
    m = Master(f"tcp://127.0.0.1:{server.port}", timeout=2.0, backend=backend.BACKEND)
    link = m._link
    # a back-off no test step can outlast: the due time is set by hand below
    link._revive.reconnect = Reconnect(Backoff(initial=60.0, maximum=60.0, jitter=0.0))
    try:
        assert m.read_holding_registers(1, 0, 1) == [1000]
        server.stop()
        with pytest.raises(PortError, match=r"closed the connection|send failed|receive failed"):
            m.read_holding_registers(1, 0, 1)
        caplog.set_level(logging.INFO, logger="pyrtu.drivers.master")
        with pytest.raises(PortError, match="cannot connect"):  # the first attempt
            m.read_holding_registers(1, 0, 1)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "cannot connect" in warnings[0].getMessage()
        retry_at = link._revive.reconnect.retry_at
        assert retry_at is not None
        server.start()  # back, but the next attempt is not due yet: no attempt made
        with pytest.raises(PortError, match=r"not connected \(.*cannot connect.*\); the next"):
            m.read_holding_registers(1, 0, 1)
        assert link._client.broken
        # at the due time: an attempt, which works now
        link._revive.reconnect._retry_at = 0.0
        assert m.read_holding_registers(1, 1, 1) == [1001]
        assert not link._client.broken and link._revive.reconnect.retry_at is None
        infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        assert any("reconnected after 1 failed attempts" in text for text in infos)
        assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    finally:
        m.close()


def test_a_closed_master_does_not_reconnect(server: Restartable, backend: ModuleType) -> None:
    m = Master(f"tcp://127.0.0.1:{server.port}", timeout=2.0, backend=backend.BACKEND)
    assert m.read_holding_registers(1, 0, 1) == [1000]
    m.close()
    with pytest.raises(PortError, match="the master is closed"):
        m.read_holding_registers(1, 0, 1)
    assert m._link._client.broken  # (no new connection was made)


def test_the_client_reconnects_in_place(server: Restartable, backend: ModuleType) -> None:
    client = TcpClient(f"tcp://127.0.0.1:{server.port}", timeout=2.0, backend=backend.BACKEND)
    try:
        assert client.request(1, READ_0) == bytes((3, 2, 0x03, 0xE8))
        assert not client.broken
        client._sock.shutdown(socket.SHUT_RDWR)  # the connection fails under the client
        with pytest.raises(PortError):
            client.request(1, READ_0)
        assert client.broken
        client.reconnect()
        assert not client.broken
        assert client.request(1, READ_0) == bytes((3, 2, 0x03, 0xE8))
        server.stop()
        with pytest.raises(PortError, match="cannot connect"):
            client.reconnect()
        assert client.broken
        with pytest.raises(PortError, match=r"unusable: .*cannot connect"):
            client.request(1, READ_0)
    finally:
        client.close()
    client.close()  # (twice: nothing more)


def test_reset_keeps_the_counters_and_transaction_ids() -> None:
    proto = TcpClientProtocol(timeout=1.0, max_in_flight=4, where="tcp://h:502")
    tid, data = proto.send_request(1, READ_0, 0.0)
    proto.send_request(1, READ_0, 0.0)
    proto.receive_data(data[:4], 0.1)  # half an answer's header: a partial ADU
    proto.connection_lost("gone")
    assert proto.broken is not None and proto.in_flight == 0
    assert [type(r[1]) for r in iter(proto.next_result, None)] == [PortError, PortError]
    with pytest.raises(PortError, match="unusable"):
        proto.send_request(1, READ_0, 0.2)
    proto.reset()
    assert proto.broken is None and proto.in_flight == 0
    nxt, data2 = proto.send_request(1, READ_0, 0.3)
    assert nxt == tid + 2  # the ids go on
    answer = data2[:4] + bytes((0, 5, 1, 3, 2, 0, 9))  # length 5: unit, fc, count, value
    proto.receive_data(answer, 0.4)  # nothing of the old stream is left in the framer
    assert proto.next_result() == (nxt, bytes((3, 2, 0, 9)))
    assert proto.counters["requests"] == 3 and proto.counters["responses"] == 1


def test_the_async_master_reconnects_after_the_server_restarted(server: Restartable) -> None:
    async def main() -> None:
        async with AsyncMaster(f"tcp://127.0.0.1:{server.port}", timeout=2.0) as m:
            # a back-off no test step can outlast: the due time is set by hand below
            m._link._revive.reconnect = Reconnect(Backoff(initial=60.0, maximum=60.0, jitter=0.0))
            assert await m.read_holding_registers(1, 0, 2) == [1000, 1001]
            server.stop()
            await until_broken(m._link._client)  # the loop hears the server close
            with pytest.raises(PortError, match="cannot connect"):
                await m.read_holding_registers(1, 0, 2)
            with pytest.raises(PortError, match="the next attempt in"):
                await m.read_holding_registers(1, 0, 2)
            server.start()
            m._link._revive.reconnect._retry_at = 0.0  # (due now)
            assert await m.read_holding_registers(1, 2, 2) == [1002, 1003]
            with pytest.raises(ExceptionResponseError):
                await m.read_holding_registers(1, 60000, 1)
            assert m.counters["requests"] == 3 and m.counters["responses"] == 2
        with pytest.raises(PortError, match="the master is closed"):
            await m.read_holding_registers(1, 0, 1)

    asyncio.run(main())


def test_the_asyncio_client_reconnects_in_place(server: Restartable) -> None:
    """`AsyncTcpClient.reconnect`: a request in flight fails (it may have been sent),
    the counters go on; a server that stays away leaves it broken, saying why."""

    async def main() -> None:
        silent = socket.create_server(("127.0.0.1", 0))  # accepts (its backlog), never answers
        try:
            url = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
            client = await AsyncTcpClient.connect(url, timeout=5.0)
            pending = asyncio.ensure_future(client.request(1, READ_0))
            await asyncio.sleep(0.05)
            assert not pending.done()
            await client.reconnect()
            with pytest.raises(PortError, match="reconnecting"):
                await pending
            assert not client.broken and client.counters["requests"] == 1
            silent.close()
            with pytest.raises(PortError, match="cannot connect"):
                await client.reconnect()
            assert client.broken
            with pytest.raises(PortError, match=r"unusable: .*cannot connect"):
                await client.request(1, READ_0)
            await client.close()
        finally:
            silent.close()
        good = await AsyncTcpClient.connect(f"tcp://127.0.0.1:{server.port}", timeout=5.0)
        assert await good.request(1, READ_0) == bytes((3, 2, 0x03, 0xE8))
        await good.reconnect()
        assert await good.request(1, READ_0) == bytes((3, 2, 0x03, 0xE8))
        assert good.counters["requests"] == 2 and good.counters["responses"] == 2
        await good.close()

    asyncio.run(main())
