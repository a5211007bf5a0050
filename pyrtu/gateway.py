"""A Modbus TCP gateway: many TCP clients onto serial buses, one transaction at a time.

Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3 (the MBAP header; the unit
id addresses a device behind a gateway) and Application Protocol V1.1b, section 7
(exceptions 0x0A and 0x0B).  The parts:

* `Routes`: unit id -> bus (``--port`` repeated with unit-id ranges).
* `FairQueue`: the sans-I/O queue of one bus: one sub-queue per connection, served
  round-robin, so a client that pipelines many requests cannot starve the others;
  bounded per connection and per bus.
* `Gateway`: the asyncio driver: a listener, one `MbapFramer` per connection (and
  optionally a second listener for RTU over TCP, one RTU framer per connection), one
  worker per bus that runs one transaction at a time through the bus's `request`
  (`pyrtu.aio.AsyncMaster`, whose sans-I/O engine keeps t3.5 and nothing more).

What the gateway answers itself (transaction id, protocol id and unit id copied
from the request, [TCP] 3.1.3):

* unit id with no bus: exception 0x0A, gateway path unavailable ([AP] 7: "the
  gateway was unable to allocate an internal communication path"); also when a
  bus's port failed (`PortError`).
* no valid answer from the device within the bus's timeout (after its retries):
  exception 0x0B, gateway target device failed to respond ([AP] 7); also when a
  bus object raises anything unexpected (logged with its trace; the bus goes on).
* queue full (this connection already has ``max_queued_per_connection`` requests
  waiting, or the bus ``max_queued_per_bus``): exception 0x06, server device busy
  ([AP] 7: "the client should retransmit the message later").  Chosen over 0x0A,
  whose text also covers overload, because busy tells a client the condition is
  transient and that retrying later is right; 0x0A stays a routing answer.
* broadcast (unit 0): sent to every bus without waiting for an answer (the bus
  keeps the turnaround delay); nothing is sent back to the client, as on a serial
  line ([SL] 2.1).

A malformed MBAP header (protocol id not 0, length outside 2..254) closes that
connection only: its waiting requests are dropped, the answers already written to
it go out if it takes them within ``close_grace`` (5 s), else it is reset.  A
client that does not read its answers is reset when its unsent output passes
``max_write_buffer`` bytes: answers are written without waiting, so it never blocks
a bus worker, and its requests go on being read (and answered, 0x06 once its queue
is full) until it is reset.  Its socket's kernel send buffer is set to
``max_write_buffer`` too (Linux doubles it), so what one client can leave unread on
the gateway's host is bounded by about three times the limit, not by the kernel's
autotuned buffer (megabytes on Linux); a reset drops what the kernel still holds
(SO_LINGER 0).  A client that disconnects leaves the bus in step: a transaction
already on the wire runs to its end (its answer is dropped), the client's waiting
requests are removed from the queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
import time
from collections import OrderedDict, deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from . import _backend
from .errors import (
    GATEWAY_PATH_UNAVAILABLE,
    GATEWAY_TARGET_FAILED,
    ILLEGAL_FUNCTION,
    SLAVE_DEVICE_BUSY,
    ExceptionResponseError,
    ModbusError,
    NoResponseError,
    PortError,
)
from .frames import FrameKind

log = logging.getLogger("pyrtu.gateway")

#: Defaults of the limits (documented in the README and ``pyrtu gateway --help``).
MAX_CONNECTIONS = 64
MAX_QUEUED_PER_CONNECTION = 16
MAX_QUEUED_PER_BUS = 256
MAX_WRITE_BUFFER = 256 * 1024
CLOSE_GRACE = 5.0


def _positive_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be a positive integer, not {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be a positive integer, not {value!r}")
    return value


@dataclass(frozen=True)
class GatewayLimits:
    """Bounds on what the gateway holds (validated on construction)."""

    max_connections: int = MAX_CONNECTIONS
    max_queued_per_connection: int = MAX_QUEUED_PER_CONNECTION
    max_queued_per_bus: int = MAX_QUEUED_PER_BUS
    max_write_buffer: int = MAX_WRITE_BUFFER
    #: seconds a connection the gateway closes (a malformed header) has to take the
    #: answers still unsent to it; then it is reset
    close_grace: float = CLOSE_GRACE

    def __post_init__(self) -> None:
        for name in (
            "max_connections",
            "max_queued_per_connection",
            "max_queued_per_bus",
            "max_write_buffer",
        ):
            _positive_int(name, getattr(self, name))
        grace = self.close_grace
        if isinstance(grace, bool) or not isinstance(grace, (int, float)):
            raise TypeError(f"close_grace must be a number of seconds, not {grace!r}")
        if not 0 <= grace < float("inf"):
            raise ValueError(f"close_grace must be finite and >= 0 seconds, not {grace!r}")


# -- routing ---------------------------------------------------------------------


def parse_units(text: str) -> frozenset[int]:
    """Serial addresses from ``"1-10,20,30-31"`` (1..247; 0 is the broadcast)."""
    units: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        lo_text, sep, hi_text = part.partition("-")
        try:
            lo = int(lo_text, 0)
            hi = int(hi_text, 0) if sep else lo
        except ValueError:
            raise ValueError(f"unit ids: {part!r} is not a number or a range A-B") from None
        if not (1 <= lo <= hi <= 247):
            raise ValueError(f"unit ids: {part!r} is outside 1..247 or not ascending")
        units.update(range(lo, hi + 1))
    return frozenset(units)


class Routes:
    """Unit id -> (bus index, slave address); every unit on at most one bus.

    Per bus: unit ids (the unit id is the slave address) or a mapping unit id ->
    slave address (a TCP server maps 0xFF, "the server itself", to its device)."""

    def __init__(self, units_per_bus: Sequence[Iterable[int] | Mapping[int, int]]) -> None:
        self._route: dict[int, tuple[int, int]] = {}
        for index, units in enumerate(units_per_bus):
            pairs = units.items() if isinstance(units, Mapping) else ((u, u) for u in units)
            for unit, slave in pairs:
                if not 1 <= unit <= 255:
                    raise ValueError(f"unit id {unit} is outside 1..255")
                if unit in self._route:
                    raise ValueError(
                        f"unit id {unit} is on bus {self._route[unit][0]} and bus {index}"
                    )
                self._route[unit] = (index, slave)
        self.buses = len(units_per_bus)

    def route(self, unit: int) -> tuple[int, int] | None:
        """(bus index, slave address) of a unit id, or None when no bus carries it."""
        return self._route.get(unit)


# -- the fair queue (sans-I/O) -------------------------------------------------------


@dataclass(slots=True)
class Job:
    """A request waiting for (or on) a bus."""

    conn: int  # connection id
    transaction: int
    unit: int  # the unit id of the request (copied into the answer)
    slave: int  # the address on the bus
    pdu: bytes


class QueueFull(Exception):
    """The connection's or the bus's queue is full (answered with exception 0x06)."""


class FairQueue:
    """Requests of many connections for one bus, served round-robin by connection."""

    def __init__(self, max_per_connection: int, max_total: int) -> None:
        self.max_per_connection = max_per_connection
        self.max_total = max_total
        self._queues: OrderedDict[int, deque[Job]] = OrderedDict()
        self._total = 0

    def __len__(self) -> int:
        return self._total

    def queued(self, conn: int) -> int:
        q = self._queues.get(conn)
        return len(q) if q else 0

    def submit(self, job: Job) -> None:
        """Queue ``job``; `QueueFull` when a bound would be passed."""
        if self._total >= self.max_total:
            raise QueueFull(f"{self._total} requests wait for this bus")
        q = self._queues.get(job.conn)
        if q is None:
            q = self._queues[job.conn] = deque()
        elif len(q) >= self.max_per_connection:
            raise QueueFull(f"connection {job.conn} has {len(q)} requests waiting")
        q.append(job)
        self._total += 1

    def pop(self) -> Job | None:
        """The next job: the head of the connection whose turn it is."""
        if not self._queues:
            return None
        queues = self._queues
        conn = next(iter(queues))
        q = queues[conn]
        job = q.popleft()
        self._total -= 1
        if q:
            queues.move_to_end(conn)  # to the back of the round
        else:
            del queues[conn]
        return job

    def drop(self, conn: int) -> int:
        """Forget every job of ``conn``; returns how many."""
        q = self._queues.pop(conn, None)
        n = len(q) if q else 0
        self._total -= n
        return n


def exception_pdu(function: int, code: int) -> bytes:
    return bytes(((function | 0x80) & 0xFF, code))


# -- the asyncio driver -------------------------------------------------------------


class Bus(Protocol):
    """What a bus behind the gateway offers: `pyrtu.aio.AsyncMaster` (a serial
    line), `pyrtu.tcp.AsyncTcpClient` (another Modbus TCP server)."""

    async def request(self, slave: int, pdu: bytes) -> bytes | None: ...


@dataclass
class _BusState:
    bus: Bus
    queue: FairQueue
    #: what the idle worker awaits; a request for the bus resolves it (a bare future:
    #: one wake-up, none of asyncio.Event's bookkeeping)
    waiter: asyncio.Future[None] | None = None
    task: asyncio.Task[None] | None = None
    busy_seconds: float = 0.0
    transactions: int = 0

    def wake(self) -> None:
        waiter = self.waiter
        if waiter is not None:
            self.waiter = None
            if not waiter.done():
                waiter.set_result(None)


def _reset(t: asyncio.Transport) -> None:
    """Close at once with a reset: SO_LINGER 0 makes the kernel drop what is still
    unsent and send RST, instead of keeping an orphan socket that goes on offering
    answers to a client that takes none."""
    sock = t.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    t.abort()


class _Connection(asyncio.Protocol):
    def __init__(self, gateway: Gateway) -> None:
        self.gateway = gateway
        self.id = 0
        self.transport: asyncio.Transport | None = None
        self.framer = _backend.active.MbapFramer("slave")
        self.closed = False
        self.grace: asyncio.TimerHandle | None = None  # a closing connection's reset

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):  # bound the kernel's share of unread answers
                sock.setsockopt(
                    socket.SOL_SOCKET, socket.SO_SNDBUF, self.gateway.limits.max_write_buffer
                )
        self.gateway._opened(self)

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        framer = self.framer
        framer.receive_data(data)
        request = self.gateway._request
        while (ev := framer.next_event()) is not None:
            if ev.error is not None:
                self.gateway.counters["bad_headers"] += 1
                log.info("connection %d: bad MBAP header (%s): closed", self.id, ev.error)
                self.close()
                return
            adu = ev.adu  # a whole ADU: transaction id, protocol 0, length, unit, PDU
            request(self, (adu[0] << 8) | adu[1], adu[6], adu[7:])
            if self.closed:
                return

    def eof_received(self) -> bool | None:
        return None  # close our side too

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        if self.grace is not None:
            self.grace.cancel()
            self.grace = None
        self.gateway._closed(self)

    def send(self, transaction: int, unit: int, pdu: bytes) -> None:
        t = self.transport
        if self.closed or t is None or t.is_closing():
            self.gateway.counters["answers_dropped"] += 1
            return
        t.write(self.encode(transaction, unit, pdu))
        if t.get_write_buffer_size() > self.gateway.limits.max_write_buffer:
            self.gateway.counters["slow_clients"] += 1
            log.info("connection %d does not read its answers: reset", self.id)
            _reset(t)
            self.closed = True  # read none of its requests still in the chunk

    def encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
        adu: bytes = self.framer.send(transaction, unit, pdu)
        return adu

    def close(self) -> None:
        """Close: its queued requests are dropped; answers already written go out if
        the client takes them within ``close_grace``, else it is reset (a client
        that does not read would otherwise hold the connection forever: asyncio's
        close waits for the write buffer to drain)."""
        t = self.transport
        if t is not None and not self.closed:
            t.close()
            if t.get_write_buffer_size():
                loop = asyncio.get_running_loop()
                self.grace = loop.call_later(self.gateway.limits.close_grace, _reset, t)
            self.gateway._closed(self)
        self.closed = True


class _RtuConnection(_Connection):
    """A client speaking RTU over TCP (RTU frames, CRC kept, no MBAP header): framed by
    the RTU framer without wire timing (length prediction and CRC); bytes that make no
    frame are skipped as on a serial line, not a reason to close.  Answers go back in
    RTU frames; there is no transaction id (such clients send one request at a time)."""

    def __init__(self, gateway: Gateway) -> None:
        super().__init__(gateway)
        self.rtu = _backend.active.Framer("slave", t15=0, t35=0)
        self.timer: asyncio.TimerHandle | None = None

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        self.rtu.receive_data(data, time.monotonic())
        self._events()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        super().connection_lost(exc)

    def _on_timer(self) -> None:
        self.timer = None
        if not self.closed:
            self.rtu.handle_timer(time.monotonic())
            self._events()

    def _events(self) -> None:
        # bytes that make no frame yet wait for the framer's flush timeout (a silence)
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        when = self.rtu.timer()
        if when is not None:
            loop = asyncio.get_running_loop()
            self.timer = loop.call_later(max(0.0, when - time.monotonic()), self._on_timer)
        while (ev := self.rtu.next_event()) is not None:
            if ev.error is not None:
                self.gateway.counters["rtu_discarded_bytes"] += len(ev.adu)
                continue
            if ev.kind is not FrameKind.REQUEST:
                continue
            self.gateway._request(self, 0, ev.address, ev.pdu)
            if self.closed:
                return

    def encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
        adu: bytes = _backend.active.add_crc(bytes((unit,)) + pdu)
        self.rtu.send(adu)
        return adu


class Gateway:
    """The asyncio gateway (see the module docstring).

    ``buses``: (bus, units) pairs; ``units`` are the unit ids routed to that bus
    (unit id = slave address on the bus), or a mapping unit id -> slave address.
    ``await start(host, port)`` listens; ``address`` is then the (host, port)
    bound; ``await close()`` stops.
    """

    def __init__(
        self,
        buses: Sequence[tuple[Bus, Iterable[int] | Mapping[int, int]]],
        limits: GatewayLimits | None = None,
    ) -> None:
        if not buses:
            raise ValueError("a gateway needs at least one bus")
        self.limits = limits or GatewayLimits()
        self.routes = Routes([units for _, units in buses])
        lim = self.limits
        self._buses = [
            _BusState(bus, FairQueue(lim.max_queued_per_connection, lim.max_queued_per_bus))
            for bus, _ in buses
        ]
        self._connections: dict[int, _Connection] = {}
        self._next_id = 0
        self._server: asyncio.Server | None = None
        self._rtu_server: asyncio.Server | None = None
        self.address: tuple[str, int] | None = None
        self.rtu_address: tuple[str, int] | None = None
        self.counters = dict.fromkeys(
            (
                "connections",
                "refused",
                "requests",
                "answers",
                "broadcasts",
                "exceptions",
                "no_route",
                "timeouts",
                "busy",
                "bad_headers",
                "slow_clients",
                "answers_dropped",
                "jobs_dropped",
                "rtu_discarded_bytes",
            ),
            0,
        )

    # ---------------------------------------------------------------- running

    async def start(
        self, host: str = "127.0.0.1", port: int = 502, rtu: tuple[str, int] | None = None
    ) -> Gateway:
        """Listen for Modbus TCP on host:port and, with ``rtu=(host, port)``, for RTU
        over TCP there (``rtu_address``)."""
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(lambda: _Connection(self), host, port)
        sock = self._server.sockets[0].getsockname()
        self.address = (str(sock[0]), int(sock[1]))
        if rtu is not None:
            self._rtu_server = await loop.create_server(lambda: _RtuConnection(self), *rtu)
            sock = self._rtu_server.sockets[0].getsockname()
            self.rtu_address = (str(sock[0]), int(sock[1]))
        for state in self._buses:
            state.task = asyncio.ensure_future(self._worker(state))
        return self

    async def close(self) -> None:
        for server in (self._server, self._rtu_server):
            if server is not None:
                server.close()
        for conn in list(self._connections.values()):
            conn.close()
        for state in self._buses:
            if state.task is not None:
                state.task.cancel()
        for state in self._buses:
            if state.task is not None:
                try:
                    await state.task
                except asyncio.CancelledError:
                    pass
        for server in (self._server, self._rtu_server):
            if server is not None:
                await server.wait_closed()

    async def __aenter__(self) -> Gateway:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def stats(self) -> dict[str, object]:
        """Counters, open connections, queue lengths and bus occupancy."""
        return {
            **self.counters,
            "open_connections": len(self._connections),
            "queued": [len(s.queue) for s in self._buses],
            "bus_transactions": [s.transactions for s in self._buses],
            "bus_busy_seconds": [round(s.busy_seconds, 6) for s in self._buses],
            "unsent_bytes": sum(
                c.transport.get_write_buffer_size()
                for c in self._connections.values()
                if c.transport is not None
            ),
        }

    # ---------------------------------------------------------- connections

    def _opened(self, conn: _Connection) -> None:
        if len(self._connections) >= self.limits.max_connections:
            self.counters["refused"] += 1
            log.info("connection refused: %d open", len(self._connections))
            conn.closed = True
            assert conn.transport is not None
            conn.transport.abort()  # nothing was written to it: a plain close
            return
        self._next_id += 1
        conn.id = self._next_id
        self._connections[conn.id] = conn
        self.counters["connections"] += 1

    def _closed(self, conn: _Connection) -> None:
        if self._connections.pop(conn.id, None) is None:
            return
        for state in self._buses:
            self.counters["jobs_dropped"] += state.queue.drop(conn.id)

    def _request(self, conn: _Connection, transaction: int, unit: int, pdu: bytes) -> None:
        counters = self.counters
        counters["requests"] += 1
        if not 1 <= pdu[0] <= 127:  # [AP] 4.1: function codes 1..127; the rest is no request
            self._answer(conn, transaction, unit, exception_pdu(pdu[0], ILLEGAL_FUNCTION))
            return
        if unit == 0:
            counters["broadcasts"] += 1
            for state in self._buses:
                self._submit(state, Job(conn.id, transaction, 0, 0, pdu), conn)
            return
        route = self.routes.route(unit)
        if route is None:
            counters["no_route"] += 1
            self._answer(conn, transaction, unit, exception_pdu(pdu[0], GATEWAY_PATH_UNAVAILABLE))
            return
        self._submit(self._buses[route[0]], Job(conn.id, transaction, unit, route[1], pdu), conn)

    def _submit(self, state: _BusState, job: Job, conn: _Connection) -> None:
        try:
            state.queue.submit(job)
        except QueueFull as exc:
            self.counters["busy"] += 1
            log.debug("connection %d: %s: busy", conn.id, exc)
            if job.unit != 0:
                self._answer(
                    conn, job.transaction, job.unit, exception_pdu(job.pdu[0], SLAVE_DEVICE_BUSY)
                )
            return
        state.wake()

    def _answer(self, conn: _Connection, transaction: int, unit: int, pdu: bytes) -> None:
        if pdu[0] & 0x80:
            self.counters["exceptions"] += 1
        else:
            self.counters["answers"] += 1
        conn.send(transaction, unit, pdu)

    # ---------------------------------------------------------------- buses

    async def _worker(self, state: _BusState) -> None:
        """One transaction at a time on the bus; never raises but CancelledError (the
        gateway is closing)."""
        loop = asyncio.get_running_loop()
        queue = state.queue
        bus = state.bus
        connections = self._connections
        counters = self.counters
        monotonic = time.monotonic
        while True:
            job = queue.pop()
            if job is None:
                state.waiter = waiter = loop.create_future()
                await waiter
                continue
            if job.conn not in connections:
                continue
            started = monotonic()
            try:
                answer = await bus.request(job.slave, job.pdu)
            except Exception as exc:  # (CancelledError is no Exception: it ends the worker)
                answer = self._failed(job, exc)
            else:
                if job.slave == 0:
                    answer = None  # a broadcast: nothing to answer
                elif not answer:
                    answer = self._failed(
                        job,
                        NoResponseError(f"unit {job.unit}: no answer PDU", job.unit, job.pdu[0]),
                    )
            state.transactions += 1
            state.busy_seconds += monotonic() - started
            conn = connections.get(job.conn)
            if conn is None:
                if answer is not None:
                    counters["answers_dropped"] += 1
            elif answer is not None:
                self._answer(conn, job.transaction, job.unit, answer)

    def _failed(self, job: Job, exc: Exception) -> bytes | None:
        """The gateway's answer when the bus's request raised ``exc`` (None for a
        broadcast): the device's exception, 0x0B when it did not answer (within the
        timeout, after the retries, or not validly), 0x0A when the bus is unavailable."""
        function = job.pdu[0]
        if isinstance(exc, ExceptionResponseError):
            return None if job.slave == 0 else exception_pdu(function, exc.code)
        if isinstance(exc, PortError):
            log.warning("bus unavailable: %s", exc)
            return None if job.slave == 0 else exception_pdu(function, GATEWAY_PATH_UNAVAILABLE)
        if isinstance(exc, (ModbusError, ValueError, RuntimeError)):
            # no answer, a garbled answer after the retries, or a request the bus refuses
            if not isinstance(exc, NoResponseError):
                log.info("unit %d: %s", job.unit, exc)
        else:  # a bus's bug: the bus goes on, the client gets an answer, the log the trace
            log.error("unit %d: the bus failed", job.unit, exc_info=exc)
        if job.slave == 0:
            return None
        self.counters["timeouts"] += 1
        return exception_pdu(function, GATEWAY_TARGET_FAILED)
