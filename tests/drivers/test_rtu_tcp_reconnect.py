"""An ``rtu+tcp://`` master whose device server goes away and comes back reconnects:
the device server is socat joining a TCP listener on a free loopback port to a
pseudo-terminal, a pyrtu `Slave` serving a store on the pty (as tests/tcp's
``rtu+tcp://`` tests run one).  Gone: the slave closed and socat stopped (its
connection closed); back: socat listening on the same port again, a new slave over
the same store.  The call that meets the closed connection raises `PortError` (not a
timeout); while the server is away a call raises `PortError` at once, naming the URL
and the next attempt, and nothing connects before the back-off's time
(`pyrtu.drivers.reconnect`); then the master reads the values the test wrote into
the store, its counters going on.  A connection reset is a `PortError` too.  A
closed master stays closed; a pyserial object the user made (`rtu_over_tcp`) is
not reconnected.  `Master` and `AsyncMaster`, on the C core and the twin; and a
poller's ``rtu+tcp://`` bus (its own reopen, `pyrtu.poller`)."""

from __future__ import annotations

import asyncio
import logging
import os
import re
import socket
import struct
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType

import pytest
from peers.tools import free_tcp_port
from ptylink import make_store
from revival import schedule
from waiting import wait_for

from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import PortError
from pyrtu.poller import Bus, Point, Poller, PortState, Update, make_config
from pyrtu.poller.events import Event
from pyrtu.tcp import rtu_over_tcp

#: the words of a call while the server is away, before the back-off's time
NOT_DUE = r"not connected \(.*cannot connect.*\); the next attempt in (\d+\.\d+) s"
#: the words of the call that meets a connection closed or reset by the server
GONE = r"^socket://127\.0\.0\.1:\d+: (read|write) failed: "
#: a safety net for awaited conditions, not a measurement
PATIENCE = 30.0
#: /proc/net/tcp's states
ESTABLISHED, LISTEN = "01", "0A"


def sockets(port: int, state: str, local: bool) -> int:
    """IPv4 TCP sockets on this machine in ``state`` whose local (else remote) port
    is ``port``."""
    count = 0
    with open("/proc/net/tcp") as table:
        next(table)
        for line in table:
            fields = line.split()
            address = fields[1] if local else fields[2]
            if fields[3] == state and int(address.rsplit(":", 1)[1], 16) == port:
                count += 1
    return count


class DeviceServer:
    """A serial device server on 127.0.0.1:``port`` (socat: TCP listener to a pty),
    a pyrtu `Slave` (address 1) serving ``store`` on the pty; `stop` and `start`
    take it away and bring it back on the same port."""

    def __init__(self, where: Path, backend: str | None = None) -> None:
        self.port = free_tcp_port()
        self.url = f"rtu+tcp://127.0.0.1:{self.port}"
        self.pty = where / "device-server-tty"
        self.store = make_store()
        self.backend = backend
        self.proc: subprocess.Popen[bytes] | None = None
        self.slave: Slave | None = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [
                "socat",
                f"PTY,link={self.pty},raw,echo=0",
                f"TCP-LISTEN:{self.port},bind=127.0.0.1,reuseaddr",
            ],
            stderr=subprocess.DEVNULL,
        )
        give_up = time.monotonic() + PATIENCE
        while not (self.pty.exists() and sockets(self.port, LISTEN, True)):
            assert self.proc.poll() is None and time.monotonic() < give_up, "socat did not start"
            time.sleep(0.01)
        self.slave = Slave(str(self.pty), 1, self.store, parity="N", t35=0, backend=self.backend)
        self.slave.start()

    def stop(self) -> None:
        assert self.proc is not None and self.slave is not None
        self.slave.close()
        self.proc.terminate()  # its connection closed, its listener too
        self.proc.wait(PATIENCE)
        if self.pty.is_symlink():
            self.pty.unlink()
        self.proc = self.slave = None

    def connected(self) -> int:
        """The connections made to the server (this process's: the master's) that are
        open now."""
        return sockets(self.port, ESTABLISHED, False)

    def close(self) -> None:
        if self.proc is not None:
            self.stop()


@pytest.fixture
def server(tmp_path: Path, backend: ModuleType) -> Iterator[DeviceServer]:
    s = DeviceServer(tmp_path, backend.BACKEND)
    try:
        yield s
    finally:
        s.close()


def test_the_master_reconnects_when_the_device_server_returns(
    server: DeviceServer, caplog: pytest.LogCaptureFixture
) -> None:
    m = Master(server.url, timeout=0.5, backend=server.backend)
    # a back-off no test step can outlast: the due time is set by hand below
    retry = schedule(m._link, 60.0)
    try:
        server.store.holding_registers.set_many(0, [11, 22])
        assert m.read_holding_registers(1, 0, 2) == [11, 22]
        assert server.connected() == 1
        before = m.counters
        old = m.port
        server.stop()
        # the closed connection: a port error (not a timeout), the socket closed
        with pytest.raises(PortError, match=GONE):
            m.read_holding_registers(1, 0, 2)
        assert old.closed and server.connected() == 0
        caplog.set_level(logging.INFO, logger="pyrtu.drivers.master")
        # the next call tries at once: nothing listens
        with pytest.raises(PortError, match=re.escape(server.url) + ": cannot connect"):
            m.read_holding_registers(1, 0, 2)
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1, warnings
        assert warnings[0].startswith(server.url + ": cannot connect")
        assert warnings[0].endswith("; reconnecting on the back-off")
        server.start()
        # back, but the next attempt is not due: nothing connects
        for _ in range(3):
            with pytest.raises(PortError, match=re.escape(server.url) + ": " + NOT_DUE):
                m.read_holding_registers(1, 0, 2)
        assert server.connected() == 0
        assert m.port is old and retry.down
        retry._retry_at = 0.0  # due now: the next call reconnects
        server.store.holding_registers.set_many(0, [33, 44])
        assert m.read_holding_registers(1, 0, 2) == [33, 44]
        assert server.connected() == 1 and m.port is not old and not retry.down
        m.write_register(1, 5, 555)
        assert server.store.holding_registers.get(5) == 555
        # the counters go on: the answers before and after the outage
        assert m.counters["responses"] == before["responses"] + 2
        infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        assert f"{server.url}: reconnected after 1 failed attempts" in infos, infos
        assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    finally:
        m.close()
    assert server.connected() == 0


@pytest.mark.wall_clock
def test_the_reconnect_waits_for_the_back_off(server: DeviceServer) -> None:
    """The real schedule: a call before the back-off's time fails at once, the first
    one after it reconnects (a second between attempts: room for a slow machine to
    start the server before the attempt is due)."""
    backoff = 1.0
    with Master(server.url, timeout=0.5, backend=server.backend) as m:
        retry = schedule(m._link, backoff)
        assert m.read_holding_registers(1, 0, 1) == [1000]
        server.stop()
        start = time.monotonic()
        with pytest.raises(PortError):
            m.read_holding_registers(1, 0, 1)
        # the closed connection is seen at once: not after the answer's timeout (0.5 s),
        # nor after the 0.3 s pyserial's socket:// sleeps in its close
        assert time.monotonic() - start < 0.25
        with pytest.raises(PortError, match="cannot connect"):
            m.read_holding_registers(1, 0, 1)
        failed_at = time.monotonic()
        server.start()
        start = time.monotonic()
        with pytest.raises(PortError, match=NOT_DUE) as info:
            m.read_holding_registers(1, 0, 1)
        assert time.monotonic() - start < 0.1  # at once: nothing connected, no timeout
        match = re.search(NOT_DUE, str(info.value))
        assert match is not None and 0.0 < float(match.group(1)) <= backoff
        assert server.connected() == 0
        retry_at = retry.retry_at
        assert retry_at is not None and failed_at - 0.1 < retry_at - backoff <= failed_at
        time.sleep(max(0.0, retry_at - time.monotonic()))
        server.store.holding_registers.set(0, 4321)
        assert m.read_holding_registers(1, 0, 1) == [4321]
        assert server.connected() == 1


def test_the_async_master_reconnects_when_the_device_server_returns(
    server: DeviceServer, caplog: pytest.LogCaptureFixture
) -> None:
    async def main() -> None:
        m = AsyncMaster(server.url, timeout=0.5, backend=server.backend)
        retry = schedule(m._link, 60.0)
        try:
            server.store.holding_registers.set_many(0, [11, 22])
            assert await m.read_holding_registers(1, 0, 2) == [11, 22]
            before = m.counters
            server.stop()
            with pytest.raises(PortError, match=GONE):
                await m.read_holding_registers(1, 0, 2)
            assert m.port.closed and server.connected() == 0
            with pytest.raises(PortError, match=re.escape(server.url) + ": cannot connect"):
                await m.read_holding_registers(1, 0, 2)
            server.start()
            for _ in range(3):
                with pytest.raises(PortError, match=re.escape(server.url) + ": " + NOT_DUE):
                    await m.read_holding_registers(1, 0, 2)
            assert server.connected() == 0 and retry.down
            retry._retry_at = 0.0  # due now
            server.store.holding_registers.set_many(0, [33, 44])
            assert await m.read_holding_registers(1, 0, 2) == [33, 44]
            value, _end = await m.transact("read_holding_registers", 1, 1, 1)
            assert value == [44] and server.connected() == 1 and not retry.down
            assert m.counters["responses"] == before["responses"] + 2
        finally:
            await m.close()
        assert server.connected() == 0
        with pytest.raises(PortError, match="the master is closed"):
            await m.read_holding_registers(1, 0, 1)

    caplog.set_level(logging.INFO, logger="pyrtu.drivers.master")
    asyncio.run(main())
    records = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in records] == [logging.WARNING, logging.INFO], records
    assert records[1][1] == f"{server.url}: reconnected after 1 failed attempts"


def test_a_cancelled_reconnect_is_awaited_not_repeated(server: DeviceServer) -> None:
    """An asyncio master connects on a worker thread: a request cancelled while it
    connects leaves the connect to end there; the next request takes its
    connection (one connection, not two), and `close` closes it."""

    async def main() -> None:
        m = AsyncMaster(server.url, timeout=0.5, backend=server.backend)
        schedule(m._link, 60.0)
        try:
            assert await m.read_holding_registers(1, 0, 1) == [1000]
            server.stop()
            with pytest.raises(PortError):
                await m.read_holding_registers(1, 0, 1)
            server.start()
            task = asyncio.ensure_future(m.read_holding_registers(1, 0, 1))
            while m._reopening is None:  # the connect is under way on its thread
                await asyncio.sleep(0)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            server.store.holding_registers.set(0, 7)
            assert await m.read_holding_registers(1, 0, 1) == [7]
            assert server.connected() == 1
        finally:
            await m.close()
        assert server.connected() == 0

    asyncio.run(main())


def accept_then_reset(listener: socket.socket) -> None:
    """Accept the master's connection and reset it (SO_LINGER 0: an RST, no FIN)."""
    peer, _ = listener.accept()
    peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    peer.close()


def test_a_reset_connection_is_a_port_error_and_reconnected(backend: ModuleType) -> None:
    """The device server resets the connection: `PortError` (not a timeout), the
    socket closed, the next call connects again (refused here: the listener gone)."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(PATIENCE)
        url = f"rtu+tcp://127.0.0.1:{listener.getsockname()[1]}"
        m = Master(url, timeout=0.5, backend=backend.BACKEND)
        accept_then_reset(listener)
    try:
        with pytest.raises(PortError, match=GONE):
            m.read_holding_registers(1, 0, 1)
        assert m.port.closed
        with pytest.raises(PortError, match=re.escape(url) + ": cannot connect"):
            m.read_holding_registers(1, 0, 1)
    finally:
        m.close()

    async def main() -> None:
        with socket.create_server(("127.0.0.1", 0)) as listener:
            listener.settimeout(PATIENCE)
            url = f"rtu+tcp://127.0.0.1:{listener.getsockname()[1]}"
            am = AsyncMaster(url, timeout=0.5, backend=backend.BACKEND)
            accept_then_reset(listener)
        try:
            with pytest.raises(PortError, match=GONE):
                await am.read_holding_registers(1, 0, 1)
            assert am.port.closed
            with pytest.raises(PortError, match=re.escape(url) + ": cannot connect"):
                await am.read_holding_registers(1, 0, 1)
        finally:
            await am.close()

    asyncio.run(main())


def test_a_closed_master_stays_closed(server: DeviceServer) -> None:
    m = Master(server.url, timeout=0.5, backend=server.backend)
    schedule(m._link, 60.0)._retry_at = 0.0
    assert m.read_holding_registers(1, 0, 1) == [1000]
    server.stop()
    with pytest.raises(PortError):
        m.read_holding_registers(1, 0, 1)
    m.close()
    server.start()
    for _ in range(2):
        with pytest.raises(PortError, match="the master is closed"):
            m.read_holding_registers(1, 0, 1)
    assert server.connected() == 0


def test_a_socket_the_user_made_is_not_reconnected(server: DeviceServer) -> None:
    """``Master(rtu_over_tcp(url))``: the pyserial object is the user's, not ours to
    make again: its calls fail as long as it is broken, no connection is made."""
    sock = rtu_over_tcp(server.url)
    m = Master(sock, t35=0, timeout=0.5, backend=server.backend)
    try:
        schedule(m._link, 60.0)._retry_at = 0.0
        assert m.read_holding_registers(1, 0, 1) == [1000]
        server.stop()
        server.start()
        for _ in range(3):
            with pytest.raises(PortError) as info:
                m.read_holding_registers(1, 0, 1)
            assert "cannot connect" not in str(info.value)
            assert "not connected" not in str(info.value)
        assert m.port.serial is sock and sock.is_open
        assert server.connected() == 0
    finally:
        m.close()
        sock.close()


def updates(events: list[Event], start: int = 0) -> list[object]:
    return [e.value for e in events[start:] if isinstance(e, Update)]


def port_states(events: list[Event]) -> list[PortState]:
    return [e for e in events if isinstance(e, PortState)]


@pytest.mark.parametrize("master", ["aio", "thread"])
def test_a_poller_bus_on_rtu_tcp_comes_back(tmp_path: Path, master: str) -> None:
    """The poller's ``rtu+tcp://`` bus: the device server gone is one `PortState`
    (down), its return another (up), and the values polled then are the store's."""
    server = DeviceServer(tmp_path)
    point = Point("x", "dev", 1, "holding", 0, interval=0.05)
    bus = Bus("dev", server.url, {"timeout": 0.5}, backoff=0.1, max_backoff=0.4)

    async def until(condition: Callable[[], bool], what: str) -> None:
        await wait_for(condition, what, PATIENCE)

    async def main() -> list[Event]:
        poller = Poller(make_config([bus], [point]), master=master, changes_only=False)
        events: list[Event] = []
        poller.on_event(events.append)
        async with poller:
            server.store.holding_registers.set(0, 111)
            await until(lambda: 111 in updates(events), "the first value")
            server.stop()
            await until(lambda: len(port_states(events)) == 1, "the bus down")
            await asyncio.sleep(0.5)  # attempts that fail again: not reported again
            assert len(port_states(events)) == 1 and poller.port_state("dev") == "down"
            server.store.holding_registers.set(0, 222)
            mark = len(events)
            server.start()
            await until(lambda: len(port_states(events)) == 2, "the bus up again")
            await until(lambda: 222 in updates(events, mark), "the value after the outage")
            assert set(updates(events, mark)) == {222}
            return list(events)

    try:
        events = asyncio.run(main())
    finally:
        server.close()
    down, up = port_states(events)
    assert (down.up, up.up) == (False, True) and down.port == up.port == server.url
    assert up.attempts >= 2


def test_no_descriptor_is_left_open(server: DeviceServer) -> None:
    """Each connection the master made is closed when it failed: after several
    outages and the close, the process has the descriptors it had."""
    fds = len(os.listdir("/proc/self/fd"))
    m = Master(server.url, timeout=0.5, backend=server.backend)
    retry = schedule(m._link, 60.0)
    try:
        for value in (5, 6, 7):
            server.store.holding_registers.set(0, value)
            assert m.read_holding_registers(1, 0, 1) == [value]
            server.stop()
            with pytest.raises(PortError):
                m.read_holding_registers(1, 0, 1)
            server.start()
            retry._retry_at = 0.0
    finally:
        m.close()
    assert len(os.listdir("/proc/self/fd")) == fds
