"""A serial master whose port vanished (a USB-RS485 adapter pulled out) reopens it when
it returns: a pseudo-terminal pair reached by a symlink the test controls (as
/dev/serial/by-id/... links are), a pyrtu `Slave` answering on its other end.  Pulled:
the pty's master end closed and the symlink removed; plugged again: a new pty, the
symlink pointed at it, a new slave over the same store.  While the port is down a
call raises `PortError` at once, naming the port and the next attempt, and nothing
opens the port before the back-off's time (`pyrtu.drivers.reconnect`); then the
master reads the values the test wrote into the slave's store, its counters going
on.  A closed master stays closed; a pyserial object the user opened is not
reopened.  `Master` and `AsyncMaster`, on the C core and the twin."""

from __future__ import annotations

import asyncio
import logging
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import serial
from ptylink import PtyLink, make_store
from revival import schedule

from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import PortError

#: the words of a call while the port is down, before the back-off's time
NOT_DUE = r"not open \(.*cannot open.*\); the next attempt in (\d+\.\d+) s"


class Adapter:
    """A USB-RS485 adapter the test plugs in and pulls out: the master's end is
    ``path``, a symlink to a pty (`PtyLink` side a); a pyrtu `Slave` serves ``store``
    on side b."""

    def __init__(self, where: Path, backend: str) -> None:
        self.path = str(where / "usb-FTDI_USB-RS485_Cable_FT1234-if00-port0")
        self.store = make_store()
        self.backend = backend
        self.link: PtyLink | None = None
        self.slave: Slave | None = None
        self.plug()

    def plug(self) -> None:
        self.link = PtyLink()
        self.slave = Slave(self.link.path_b, 1, self.store, parity="N", backend=self.backend)
        self.slave.start()
        os.symlink(self.link.path_a, self.path)

    def pull(self) -> None:
        assert self.link is not None and self.slave is not None
        self.slave.close()
        self.link.close()  # the pty's master end closed: the tty end reports EIO
        os.unlink(self.path)
        self.link = self.slave = None

    def opened(self) -> int:
        """How many descriptors of this process (besides the pty link's own) are open
        on the pty the symlink names now."""
        assert self.link is not None
        tty = self.link.path_a
        mine = 0
        for fd in os.listdir("/proc/self/fd"):
            try:
                mine += os.readlink(f"/proc/self/fd/{fd}") == tty
            except OSError:
                pass
        return mine - 1

    def heard(self) -> bytes:
        """What reached the plugged adapter from the master (its side a's writes)."""
        assert self.link is not None
        self.link.settle()
        return self.link.wire("a")

    def close(self) -> None:
        if self.link is not None:
            self.pull()


@pytest.fixture
def adapter(tmp_path: Path, backend: ModuleType) -> Iterator[Adapter]:
    a = Adapter(tmp_path, backend.BACKEND)
    try:
        yield a
    finally:
        a.close()


def test_the_master_reopens_its_port_when_the_adapter_returns(
    adapter: Adapter, caplog: pytest.LogCaptureFixture
) -> None:
    m = Master(adapter.path, parity="N", timeout=0.5, backend=adapter.backend)
    # a back-off no test step can outlast: the due time is set by hand below
    retry = schedule(m._link, 60.0)
    try:
        adapter.store.holding_registers.set_many(0, [11, 22])
        assert m.read_holding_registers(1, 0, 2) == [11, 22]
        before = m.counters
        old = m.port
        adapter.pull()
        with pytest.raises(PortError, match=re.escape(adapter.path)):  # EIO
            m.read_holding_registers(1, 0, 2)
        caplog.set_level(logging.INFO, logger="pyrtu.drivers.master")
        # the next call tries at once: the path is gone
        with pytest.raises(PortError, match=re.escape(adapter.path) + ": cannot open"):
            m.read_holding_registers(1, 0, 2)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "cannot open" in warnings[0].getMessage()
        adapter.plug()
        # back, but the next attempt is not due: no attempt, the port untouched
        for _ in range(3):
            with pytest.raises(PortError, match=re.escape(adapter.path) + ": " + NOT_DUE):
                m.read_holding_registers(1, 0, 2)
        assert adapter.opened() == 0 and adapter.heard() == b""
        assert m.port is old and retry.down
        retry._retry_at = 0.0  # due now: the next call reopens the port
        adapter.store.holding_registers.set_many(0, [33, 44])
        assert m.read_holding_registers(1, 0, 2) == [33, 44]
        assert adapter.opened() == 1 and m.port is not old and not retry.down
        m.write_register(1, 5, 555)
        assert adapter.store.holding_registers.get(5) == 555
        # the counters go on: the answers before and after the outage
        assert m.counters["responses"] == before["responses"] + 2
        infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        assert any("reopened after 1 failed attempts" in text for text in infos)
        assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    finally:
        m.close()
    assert adapter.opened() == 0


@pytest.mark.wall_clock
def test_the_reopen_waits_for_the_back_off(adapter: Adapter) -> None:
    """The real schedule: a call before the back-off's time fails at once, the first
    one after it reopens (a second between attempts: room for a slow machine to plug
    the adapter in before the attempt is due)."""
    backoff = 1.0
    with Master(adapter.path, parity="N", timeout=0.5, backend=adapter.backend) as m:
        retry = schedule(m._link, backoff)
        assert m.read_holding_registers(1, 0, 1) == [1000]
        adapter.pull()
        with pytest.raises(PortError):
            m.read_holding_registers(1, 0, 1)
        with pytest.raises(PortError, match="cannot open"):
            m.read_holding_registers(1, 0, 1)
        failed_at = time.monotonic()
        adapter.plug()
        start = time.monotonic()
        with pytest.raises(PortError, match=NOT_DUE) as info:
            m.read_holding_registers(1, 0, 1)
        assert time.monotonic() - start < 0.1  # at once: no port touched, no timeout
        match = re.search(NOT_DUE, str(info.value))
        assert match is not None and 0.0 < float(match.group(1)) <= backoff
        assert adapter.opened() == 0 and adapter.heard() == b""
        retry_at = retry.retry_at
        assert retry_at is not None and failed_at - 0.1 < retry_at - backoff <= failed_at
        time.sleep(max(0.0, retry_at - time.monotonic()))
        adapter.store.holding_registers.set(0, 4321)
        assert m.read_holding_registers(1, 0, 1) == [4321]
        assert adapter.opened() == 1


def test_the_async_master_reopens_its_port_when_the_adapter_returns(adapter: Adapter) -> None:
    async def main() -> None:
        m = AsyncMaster(adapter.path, parity="N", timeout=0.5, backend=adapter.backend)
        retry = schedule(m._link, 60.0)
        try:
            adapter.store.holding_registers.set_many(0, [11, 22])
            assert await m.read_holding_registers(1, 0, 2) == [11, 22]
            before = m.counters
            adapter.pull()
            with pytest.raises(PortError, match=re.escape(adapter.path)):
                await m.read_holding_registers(1, 0, 2)
            with pytest.raises(PortError, match="cannot open"):
                await m.read_holding_registers(1, 0, 2)
            adapter.plug()
            with pytest.raises(PortError, match=re.escape(adapter.path) + ": " + NOT_DUE):
                await m.read_holding_registers(1, 0, 2)
            assert adapter.opened() == 0 and adapter.heard() == b""
            retry._retry_at = 0.0  # due now
            adapter.store.holding_registers.set_many(0, [33, 44])
            assert await m.read_holding_registers(1, 0, 2) == [33, 44]
            value, _end = await m.transact("read_holding_registers", 1, 1, 1)
            assert value == [44] and adapter.opened() == 1
            assert m.counters["responses"] == before["responses"] + 2
        finally:
            await m.close()
        assert adapter.opened() == 0
        with pytest.raises(PortError, match="the master is closed"):
            await m.read_holding_registers(1, 0, 1)

    asyncio.run(main())


def test_a_closed_master_stays_closed(adapter: Adapter) -> None:
    m = Master(adapter.path, parity="N", timeout=0.5, backend=adapter.backend)
    schedule(m._link, 60.0)._retry_at = 0.0
    assert m.read_holding_registers(1, 0, 1) == [1000]
    adapter.pull()
    with pytest.raises(PortError):
        m.read_holding_registers(1, 0, 1)
    m.close()
    adapter.plug()
    for _ in range(2):
        with pytest.raises(PortError, match="the master is closed"):
            m.read_holding_registers(1, 0, 1)
    assert adapter.opened() == 0 and adapter.heard() == b""


def test_a_port_object_the_user_opened_is_not_reopened(adapter: Adapter) -> None:
    """``Master(serial_object)``: the object is the user's, not ours to open again: its
    calls fail as long as it is broken (today's behaviour), the returned adapter is
    left alone."""
    ser = serial.Serial(adapter.path, 19200, timeout=0)
    m = Master(ser, timeout=0.5, backend=adapter.backend)
    try:
        schedule(m._link, 60.0)._retry_at = 0.0
        assert m.read_holding_registers(1, 0, 1) == [1000]
        adapter.pull()
        adapter.plug()
        for _ in range(3):
            with pytest.raises(PortError) as info:
                m.read_holding_registers(1, 0, 1)
            assert "cannot open" not in str(info.value) and "not open" not in str(info.value)
        assert m.port.serial is ser and ser.is_open
        assert adapter.opened() == 0 and adapter.heard() == b""
    finally:
        m.close()
        ser.close()
