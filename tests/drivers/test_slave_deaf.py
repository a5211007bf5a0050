"""Issue 17: a slave went deaf after one long request.

After a request of about 50 ms on the wire (a write of 47 registers at 19200 baud,
answered with exception 4 or not), every later request timed out: the slave slept
through the next request's first byte for the long one's length (guessed from the
address alone), read the rest late, and the framer, shown the late bytes as if they
came after a silence of the whole nap, dropped the request as two damaged frames
(its flush timeout is 50 ms) — and never learned a shorter length.

Here: the server protocol on synthetic time (the exact sequence of the report, and
the late read that a guess too long leaves), then `Slave` and `AsyncSlave` on the
virtual bus at 9600..115200 baud with pyrtu's Master, and with minimalmodbus.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator
from types import ModuleType

import pytest
from peers.tools import minimal_instrument
from waiting import ANSWER_TIMEOUT

from pyrtu import pdu as pdus
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncSlave
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import PREPARE, Slave
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.pdu.errors import ExceptionResponseError, SlaveException
from pyrtu.protocol.datastore import DataStore
from pyrtu.protocol.server import Listen, Reply, ServerProtocol
from pyrtu.vbus import VirtualBus

ADDRESS = 5
FAILING = 1000  # writes here draw exception 4 (SLAVE DEVICE FAILURE), as cv100's did


def make_store() -> DataStore:
    store = DataStore()
    store.holding_registers.add_range(0, [1000 + i for i in range(125)])
    return store


def device_failure(unit: int, pdu: bytes) -> None:
    if pdu[0] == pdus.WRITE_MULTIPLE_REGISTERS and int.from_bytes(pdu[1:3], "big") == FAILING:
        raise SlaveException(4, "the device failed")


def long_count(line: LineConfig, seconds: float = 0.06) -> int:
    """The registers of a FC 16 request ``seconds`` on the wire (at most 123): past the
    framer's flush timeout (50 ms), where the report saw the slave go deaf."""
    return max(1, min(123, (round(seconds / line.char_time) - 9) // 2))


# ------------------------------------------------------------ synthetic time


class Line:
    """A protocol driven as `Slave` drives it, on a byte-timed line of synthetic time."""

    def __init__(self, backend: ModuleType, line: LineConfig) -> None:
        self.backend = backend
        self.char = line.char_time
        self.app = SlaveBase(ADDRESS, make_store(), line=line, backend=backend.BACKEND)
        self.app.on_request(device_failure)
        self.proto = ServerProtocol(line, self.app, backend=backend, state=self.app.line)
        self.now = 100.0

    def transact(self, message: bytes) -> bytes | None:
        """``message`` sent at the character rate after a long silence; the answer."""
        adu = bytes(self.backend.add_crc(bytes((ADDRESS,)) + message))
        proto = self.proto
        t0 = self.now + 0.2
        arrival = [t0 + (i + 1) * self.char for i in range(len(adu))]
        now, got = arrival[0], 0
        while now < t0 + 2.0:
            ready = sum(1 for t in arrival if t <= now)
            proto.receive_data(adu[got:ready], now)
            got = ready
            action = proto.next_action(now, lead=PREPARE)
            if isinstance(action, Reply):
                proto.transmitted(now + len(action.data) * self.char)
                self.now = now + len(action.data) * self.char
                return action.data
            if isinstance(action, Listen) and action.needed:  # a nap: then read it all
                now = max(now, action.until)
                continue
            # watching the port: the next byte or the protocol's deadline
            wakes = [arrival[got]] if got < len(adu) else []
            if isinstance(action, Listen):
                wakes.append(action.until)
            if not wakes:
                break
            now = max(now, min(wakes))
        self.now = now
        return None


@pytest.mark.parametrize("baud", [9600, 19200, 38400, 115200])
def test_the_reported_sequence_on_synthetic_time(backend: ModuleType, baud: int) -> None:
    """read, the ~60 ms write that draws exception 4, read, read, a long valid write,
    read: every one answered, none counted as a communication error."""
    line = LineConfig(baudrate=baud, parity="N")
    h = Line(backend, line)
    count = long_count(line)
    read = pdus.read_request(3, 0, 2)
    assert h.transact(read) is not None
    for _ in range(3):
        failing = pdus.write_registers_request(FAILING, list(range(1, count + 1)))
        assert h.transact(failing) == backend.add_crc(bytes((ADDRESS, 0x90, 4)))
        for _ in range(2):
            out = h.transact(read)
            assert out is not None and out[1] == 3, f"{baud}: a read after the long write lost"
        valid = pdus.write_registers_request(0, list(range(1, count + 1)))
        assert h.transact(valid) == backend.add_crc(bytes((ADDRESS,)) + valid[:5])
        out = h.transact(read)
        assert out is not None and out[3:7] == b"\x00\x01\x00\x02"
    assert h.app.line.counters["bus_communication_error_count"] == 0


def test_a_nap_longer_than_the_request_loses_nothing(backend: ModuleType) -> None:
    """A vendor function without a length rule is guessed at its last length: after a
    long one, a short one ends long before the nap.  Read late, its bytes are timed
    at the character rate after the first two, so it is answered at t3.5 after its
    real end (not at t3.5 after the late read)."""
    line = LineConfig(baudrate=9600, parity="N")
    h = Line(backend, line)
    h.app.register_function(0x41, lambda slave, unit, pdu: pdu[:4])
    long = bytes((0x41,)) + bytes(120)  # 124 bytes with address and CRC: 129 ms
    assert h.transact(long) is not None
    short = bytes((0x41, 1, 2, 3))
    adu = bytes(backend.add_crc(bytes((ADDRESS,)) + short))
    t0 = h.now + 0.2
    proto = h.proto
    proto.receive_data(adu[:2], t0)
    at = proto.wake_at(t0)
    # the guess: the last length, 124 bytes, for a nap of at most half the flush
    # timeout (25 ms, 24 characters): it outlasts the 7-byte request all the same
    assert at == pytest.approx(t0 + 0.025)
    proto.receive_data(adu[2:], at)  # read late, all of it
    if proto.pending is None:
        proto.handle_timer(at)
    pending = proto.pending
    assert pending is not None and pending.adu[1:5] == short
    end = t0 + (len(adu) - 2) * h.char
    assert pending.earliest == pytest.approx(end + line.t35_time)
    assert h.app.line.counters["bus_communication_error_count"] == 0


def test_the_guess_from_the_address_alone_is_short(backend: ModuleType) -> None:
    """After a long write, the next request's first byte does not put the slave to
    sleep for the long length: at most 8 bytes (a read), so a read is answered on
    time and a long request costs one more wake-up."""
    line = LineConfig(baudrate=19200, parity="N")
    h = Line(backend, line)
    assert h.transact(pdus.write_registers_request(0, list(range(47)))) is not None
    t0 = h.now + 0.2
    h.proto.receive_data(bytes((ADDRESS,)), t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 7 * h.char + line.t35_time)


# ------------------------------------------------------------- the virtual bus


@contextlib.contextmanager
def serving(kind: str, path: str, baud: int, backend: str) -> Iterator[Slave | AsyncSlave]:
    """A `Slave` (its thread) or an `AsyncSlave` (a loop in a thread) on ``path``."""
    options = dict(address=ADDRESS, store=make_store(), baudrate=baud, parity="N")
    if kind == "sync":
        slave = Slave(path, backend=backend, **options)  # type: ignore[arg-type]
        slave.on_request(device_failure)
        slave.start()
        try:
            yield slave
        finally:
            slave.close()
        assert slave.error is None
        return
    loop = asyncio.new_event_loop()
    aslave = AsyncSlave(path, backend=backend, **options)  # type: ignore[arg-type]
    aslave.on_request(device_failure)
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    try:
        asyncio.run_coroutine_threadsafe(_start(aslave), loop).result(5)
        yield aslave
    finally:
        asyncio.run_coroutine_threadsafe(aslave.close(), loop).result(5)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()
    assert aslave.error is None


async def _start(slave: AsyncSlave) -> None:
    slave.start()


@pytest.mark.wall_clock
@pytest.mark.parametrize("kind", ["sync", "async"])
def test_long_requests_and_short_reads_on_the_virtual_bus(backend: ModuleType, kind: str) -> None:
    """At 9600, 19200, 38400 and 115200 baud: the ~60 ms write that draws exception 4
    (all 123 registers at 115200, 22 ms), a long valid write, short reads between
    them; every read answered within the master's timeout (1 s, hundreds of t3.5)."""
    for baud in (9600, 19200, 38400, 115200):
        line = LineConfig(baudrate=baud, parity="N")
        count = long_count(line)
        with (
            VirtualBus(2, baudrate=baud, parity="N") as bus,
            serving(kind, bus.paths[1], baud, backend.BACKEND) as slave,
            Master(bus.paths[0], baud, parity="N", timeout=1.0) as m,
        ):
            assert m.read_holding_registers(ADDRESS, 0, 2) == [1000, 1001]
            for i in range(2):
                with pytest.raises(ExceptionResponseError) as info:
                    m.write_registers(ADDRESS, FAILING, list(range(1, count + 1)))
                assert info.value.code == 4
                assert m.read_holding_registers(ADDRESS, 0, 2) == [1000 + i, 1001 + i]
                m.write_registers(ADDRESS, 0, [1001 + i + k for k in range(count)])
                assert m.read_holding_registers(ADDRESS, 0, 2) == [1001 + i, 1002 + i]
            counters = slave.counters
            assert counters["bus_communication_error_count"] == 0, (baud, counters)
            assert counters["requests"] == 9


@pytest.mark.wall_clock
def test_minimalmodbus_reads_after_the_long_write(backend: ModuleType) -> None:
    """The report's other master: minimalmodbus at 19200 baud (its own timing, 8N1;
    it waits out its timeout on an exception response, hence the shorter one, still
    over a hundred t3.5)."""
    import minimalmodbus

    with (
        VirtualBus(2, baudrate=19200, parity="N") as bus,
        serving("sync", bus.paths[1], 19200, backend.BACKEND) as slave,
    ):
        inst = minimal_instrument(bus.paths[0], ADDRESS, baudrate=19200, timeout=ANSWER_TIMEOUT)
        try:
            assert inst.read_registers(0, 2) == [1000, 1001]
            for i in range(2):
                with pytest.raises(minimalmodbus.SlaveReportedException, match="device failure"):
                    inst.write_registers(FAILING, list(range(1, 48)))
                assert inst.read_registers(0, 2) == [1000 + i, 1001 + i]
                inst.write_registers(0, [1001 + i + k for k in range(47)])
                assert inst.read_registers(0, 2) == [1001 + i, 1002 + i]
        finally:
            inst.serial.close()
        assert slave.counters["bus_communication_error_count"] == 0


def test_a_nap_lasts_at_most_half_the_flush_timeout(backend: ModuleType) -> None:
    """A 255-byte write at 9600 baud (266 ms): naps of 25 ms at most (half the flush
    timeout), so that nothing read after one can show the framer a silence it would
    end a frame on; the write is answered at t3.5 after its end all the same."""
    line = LineConfig(baudrate=9600, parity="N")
    h = Line(backend, line)
    proto = h.proto
    naps: list[float] = []
    wake_at = proto.wake_at

    def recording(now: float, lead: float = 0.0) -> float | None:
        at = wake_at(now, lead)
        if at is not None:
            naps.append(at - now)
        return at

    proto.wake_at = recording  # type: ignore[method-assign]
    write = pdus.write_registers_request(0, list(range(123)))
    end = h.now + 0.2 + (len(write) + 3) * h.char  # its last byte (see Line.transact)
    out = h.transact(write)
    assert out == backend.add_crc(bytes((ADDRESS,)) + write[:5])
    sent = h.now - len(out) * h.char
    assert end + line.t35_time - 1e-6 <= sent <= end + line.t35_time + 1e-3
    assert max(naps) == pytest.approx(0.025)
    assert len(naps) >= 266 // 25
