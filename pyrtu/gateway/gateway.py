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
  (`pyrtu.drivers.aio.AsyncMaster`, whose sans-I/O engine keeps t3.5 and nothing more).

What the gateway answers itself (transaction id, protocol id and unit id copied
from the request, [TCP] 3.1.3):

* unit id with no bus: exception 0x0A, gateway path unavailable ([AP] 7: "the
  gateway was unable to allocate an internal communication path").
* a bus whose port failed (`PortError`: a USB adapter pulled out, a TCP peer
  gone), or was not there when the gateway started (a `ReopeningBus` that `start`
  could not open: an adapter plugged in after boot): 0x0A at once to every request
  for it while it is down ("the gateway was unable to allocate an internal
  communication path": the path to the device, not the device, is missing; 0x0B
  is kept for a device that was asked and did not answer).  The failure is
  logged once (a warning), counted (``bus_failures``; ``bus_unavailable`` counts
  the requests so answered) and shown in ``stats()["bus_down"]``; the gateway
  retries on the shared back-off schedule (`pyrtu.drivers.reconnect`): through the
  bus's ``reopen()`` if it has one, else by letting the next request through
  when a retry is due.  The other buses carry on; when the port is back, one
  log line says so.
* no valid answer from the device within the bus's timeout (after its retries):
  exception 0x0B, gateway target device failed to respond ([AP] 7); also when a
  bus object raises anything unexpected (logged with its trace; the bus goes on).
* queue full (this connection already has ``max_queued_per_connection`` requests
  waiting, or the bus ``max_queued_per_bus``): exception 0x06, server device busy
  ([AP] 7: "the client should retransmit the message later").  Chosen over 0x0A,
  whose text also covers overload, because busy tells a client the condition is
  transient and that retrying later is right; 0x0A stays a routing answer.
* broadcast (unit 0): sent to every bus that is up, without waiting for an answer
  (the bus keeps the turnaround delay); nothing is sent back to the client, as on
  a serial line ([SL] 2.1).  Unless the routes map unit 0 to a slave (``{0: 1}``,
  ``--unit-map 0=1``): [TCP] 4.4.1.2 lets a client address a TCP device with unit
  0 (or 0xFF), and such clients expect an answer.

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

Every background task (the bus workers, the sweeper of timed-out connections)
is supervised (`pyrtu.drivers.supervise`): a task that raises something unexpected
(a fault of the gateway itself, not of a bus: those are answered as above) is
logged once with its cause (one error line per run of failures), reported to
``on_task`` (a `TaskFailure`), counted (``task_failures``) and started again on the
shared back-off (``limits.backoff``).  The request the worker was serving is
answered 0x0B (gateway target device failed to respond) unless its answer was
already being written; requests for the bus meanwhile wait in its queue (0x06 once
it is full) and are served when the worker is back; the other buses carry on.

With ``udp=(host, port)`` the gateway also listens for Modbus over UDP (one ADU
per datagram, `pyrtu.gateway._udp`): each client address is a connection of the
table (policy, audit, fair queue, idle timeout and eviction as for TCP); a datagram
that is not one whole valid ADU is dropped and counted (``bad_datagrams``).  With
``port=None`` the gateway has no Modbus TCP listener (another one must be given).

Clients that do not talk cannot hold the connection table (`pyrtu.gateway._live`):
a request must be complete within ``header_timeout`` (5 s) of its first byte, a
connection with no request for ``idle_timeout`` (120 s) and nothing waiting is
closed, and when the table is full a newcomer takes the slot of a connection that
never completed a request (else the longest idle one); counted as
``header_timeouts``, ``idle_timeouts`` and ``evicted``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Protocol

from pyrtu.core._deprecated import renamed
from pyrtu.drivers.reconnect import Reconnect
from pyrtu.drivers.supervise import TaskFailure, supervise
from pyrtu.pdu.errors import (
    GATEWAY_PATH_UNAVAILABLE,
    GATEWAY_TARGET_FAILED,
    ILLEGAL_FUNCTION,
    SLAVE_DEVICE_BUSY,
    ModbusError,
    NoResponseError,
    PortError,
)
from pyrtu.security.audit import AuditTrail
from pyrtu.security.policy import Decision, Identity, Policy, beyond_loopback, is_read
from pyrtu.security.tls import TlsListen

from ._conn import _Connection, _RtuConnection, _TlsConnection
from ._engine import EngineConnection, ServerEngine
from ._live import HEADER, pick_victim
from ._plan import (
    CLOSE_GRACE,
    HEADER_TIMEOUT,
    IDLE_TIMEOUT,
    MAX_CONNECTIONS,
    MAX_QUEUED_PER_BUS,
    MAX_QUEUED_PER_CONNECTION,
    MAX_WRITE_BUFFER,
    FairQueue,
    GatewayLimits,
    Job,
    QueueFull,
    Routes,
    check_listen,
    exception_pdu,
    parse_units,
)
from ._reopen import ReopeningBus, close_bus
from ._udp import UdpListener

log = logging.getLogger("pyrtu.gateway")

#: the (client, role, reason) triples of refused requests already logged; past this
#: many the memory of them starts again (a log bounded however many clients try)
DENIALS_REMEMBERED = 4096

#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(__name__, {"Bus": ("pyrtu.gateway.gateway", "GatewayBus")})

__all__ = [
    "CLOSE_GRACE",
    "HEADER_TIMEOUT",
    "IDLE_TIMEOUT",
    "MAX_CONNECTIONS",
    "MAX_QUEUED_PER_BUS",
    "MAX_QUEUED_PER_CONNECTION",
    "MAX_WRITE_BUFFER",
    "BusEvent",
    "FairQueue",
    "Gateway",
    "GatewayBus",
    "GatewayLimits",
    "Job",
    "QueueFull",
    "ReopeningBus",
    "Routes",
    "close_bus",
    "exception_pdu",
    "parse_units",
]


#: how often `Gateway.close` cancels a task again whose code swallowed the cancel
CANCEL_AGAIN = 0.1


def _check_pair(name: str, where: object) -> None:
    """``where``: a (host, port) to listen on; TypeError/ValueError naming ``name``."""
    if not isinstance(where, tuple) or len(where) != 2:
        raise TypeError(f"{name} must be a (host, port) pair, not {where!r}")
    try:
        check_listen(*where)
    except (TypeError, ValueError) as exc:
        raise type(exc)(f"{name}: {exc}") from None


async def _cancelled(task: asyncio.Task[None]) -> None:
    """Cancel ``task`` and wait until it ends, cancelling it again every
    `CANCEL_AGAIN` seconds: a cancel can be lost under it (Python 3.11's
    ``asyncio.wait_for`` raises its operation's error instead of CancelledError when
    both come at once, as a bus reopened while the gateway closes: the reopen's
    ``except OSError`` then takes it, and the worker went on retrying forever; the
    worker also stops at its next turn once the gateway is not running)."""
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=CANCEL_AGAIN)
    if not task.cancelled() and task.exception() is not None:
        log.debug("task %s ended with %r", task.get_name(), task.exception())


class GatewayBus(Protocol):
    """What a bus behind the gateway offers: `pyrtu.drivers.aio.AsyncMaster` (a serial
    line), `pyrtu.tcp.AsyncTcpClient` (another Modbus TCP server).  ``request``
    returns the answer PDU, an exception answer too (as its bytes, as
    `pyrtu.tcp.server.LocalBus` does); a bus whose ``request`` raises
    `ExceptionResponseError` instead (`AsyncMaster`, `AsyncTcpClient`) offers
    ``exchange``, of the same shape, which the gateway calls when a bus has it: an
    exception raised is a target that failed to respond (0x0B).  A bus may also
    have ``async reopen()``, which the gateway calls to bring it back after a
    `PortError` (raising `PortError` or `OSError` while the port is still gone); and
    ``transact_now(slave, pdu)``, the same transaction as a plain call when it never
    waits (a local application: `pyrtu.tcp.server.LocalBus`), which the gateway runs
    in the request's own callback while the bus is idle (no task switch per request;
    queued behind the others otherwise, as any request)."""

    async def request(self, slave: int, pdu: bytes) -> bytes | None: ...


@dataclass(frozen=True)
class BusEvent:
    """A bus's port failed (``up`` False: the first failure of an outage, reported
    once; ``starting``: it could not be opened when the gateway started) or is back
    (``up`` True, with the outage's ``attempts`` and ``seconds``)."""

    bus: int  # its index in the gateway's buses
    name: str
    up: bool
    error: str  # what failed (the first error of the outage)
    attempts: int = 1
    seconds: float | None = None
    starting: bool = False


def _bus_name(bus: object, index: int) -> str:
    for attr in ("name", "url", "where"):
        name = getattr(bus, attr, None)
        if isinstance(name, str) and name:
            return name
    port = getattr(bus, "port", None)
    return str(getattr(port, "name", None) or f"bus {index}")


@dataclass
class _BusState:
    index: int
    bus: GatewayBus
    queue: FairQueue
    name: str
    reconnect: Reconnect
    #: what the idle worker awaits; a request for the bus resolves it (a bare future:
    #: one wake-up, none of asyncio.Event's bookkeeping)
    waiter: asyncio.Future[None] | None = None
    task: asyncio.Task[None] | None = None
    busy_seconds: float = 0.0
    transactions: int = 0
    reopen: object = field(default=None)
    #: the request the worker is serving, until its answer is being written
    current: Job | None = None
    #: the bus's transaction as a plain call (`GatewayBus`'s ``transact_now``), or None
    now: Callable[[int, bytes], bytes | None] | None = None

    def wake(self) -> None:
        waiter = self.waiter
        if waiter is not None:
            self.waiter = None
            if not waiter.done():
                waiter.set_result(None)

    def refuses(self, now: float) -> bool:
        """True while the port is down and no attempt is due through a request (a
        bus with ``reopen`` is retried by its worker; requests wait for it up)."""
        rc = self.reconnect
        return rc.down and (self.reopen is not None or not rc.due(now))


class Gateway:
    """The asyncio gateway (see the module docstring).

    ``buses``: (bus, units) pairs; ``units`` are the unit ids routed to that bus
    (unit id = slave address on the bus), or a mapping unit id -> slave address.
    ``on_bus`` is called with a `BusEvent` when a bus's port fails (once per outage)
    and when it is back; ``on_task`` with a `TaskFailure` when a background task
    raised (once per run of failures; it is started again on the back-off).
    ``await start(host, port)`` opens the `ReopeningBus` buses not opened yet (one
    whose port is not there is down: reported once, reopened on the back-off while
    the others serve) and listens; ``address`` is then the (host, port) bound;
    ``await close()`` stops.
    """

    def __init__(
        self,
        buses: Sequence[tuple[GatewayBus, Iterable[int] | Mapping[int, int]]],
        limits: GatewayLimits | None = None,
        on_bus: Callable[[BusEvent], None] | None = None,
        on_task: Callable[[TaskFailure], None] | None = None,
        *,
        policy: Policy | None = None,
        audit: AuditTrail | None = None,
        on_denied: Callable[[Identity, Decision], None] | None = None,
    ) -> None:
        if not buses:
            raise ValueError("a gateway needs at least one bus")
        self.limits = limits or GatewayLimits()
        self.routes = Routes([units for _, units in buses])
        lim = self.limits
        self._buses = [
            _BusState(
                index,
                bus,
                FairQueue(lim.max_queued_per_connection, lim.max_queued_per_bus),
                _bus_name(bus, index),
                Reconnect(lim.backoff),
                reopen=getattr(bus, "reopen", None),
                now=getattr(bus, "transact_now", None),
            )
            for index, (bus, _) in enumerate(buses)
        ]
        self._sweeper: asyncio.Task[None] | None = None
        self.on_bus = on_bus
        self.on_task = on_task
        #: the access policy of every listener (None: every request is served)
        self.policy = policy
        #: where every executed write is recorded (None: nowhere)
        self.audit = audit
        #: called once per client address and reason with a refused request's
        #: identity and `Decision` (the CLI's line on stderr)
        self.on_denied = on_denied
        self._denials_logged: set[tuple[str, str | None, str]] = set()
        #: refused requests by `Decision.kind`
        self.denied_by: dict[str, int] = {}
        #: called with (bus name, slave, seconds) for every answered transaction of a
        #: bus worker (a response or an exception response; not broadcasts): the
        #: latency histograms of ``--metrics``
        self.on_latency: Callable[[str, int, float], None] | None = None
        #: the C engine of the plain listener (`pyrtu.gateway._engine`: a `TcpServer`
        #: sets the factory before `start`), None: Python reads every connection
        self.engine_factory: Callable[[], ServerEngine] | None = None
        self.engine: ServerEngine | None = None
        self._running = False
        self._connections: dict[int, _Connection] = {}
        self._next_id = 0
        self._server: asyncio.Server | None = None
        self._rtu_server: asyncio.Server | None = None
        self._tls_server: asyncio.Server | None = None
        self._udp: UdpListener | None = None
        #: the (host, port) of the TLS listener, once started with ``tls``
        self.tls_address: tuple[str, int] | None = None
        #: the (host, port) of the UDP listener, once started with ``udp``
        self.udp_address: tuple[str, int] | None = None
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
                "header_timeouts",
                "idle_timeouts",
                "evicted",
                "bus_failures",
                "bus_recoveries",
                "bus_unavailable",
                "task_failures",
                "denied",
                "tls_failures",
                "bad_datagrams",
                "audited_writes",
                "audit_failures",
            ),
            0,
        )

    # ---------------------------------------------------------------- running

    async def start(
        self,
        host: str = "127.0.0.1",
        port: int | None = 502,
        rtu: tuple[str, int] | None = None,
        tls: TlsListen | None = None,
        udp: tuple[str, int] | None = None,
    ) -> Gateway:
        """Listen for Modbus TCP on host:port and, with ``rtu=(host, port)``, for RTU
        over TCP there (``rtu_address``), with ``tls`` (a `TlsListen`) for Modbus/TCP
        Security there (``tls_address``), with ``udp=(host, port)`` for Modbus over UDP
        there (``udp_address``); ``port=None``: no Modbus TCP listener (``address``
        stays None), one of the others must be given.  RuntimeError if already
        started; TypeError/ValueError naming the argument before anything listens."""
        if self._listeners():
            listening = (self.address, self.rtu_address, self.tls_address, self.udp_address)
            text = ", ".join("{}:{}".format(*at) for at in listening if at is not None)
            raise RuntimeError(f"the gateway already listens on {text}")
        if port is not None:
            check_listen(host, port)
        elif rtu is None and tls is None and udp is None:
            raise ValueError("port: None (no Modbus TCP listener) needs rtu, tls or udp")
        if rtu is not None:
            _check_pair("rtu", rtu)
        if tls is not None:
            if not isinstance(tls, TlsListen):
                raise TypeError(f"tls must be a pyrtu.security.tls.TlsListen, not {tls!r}")
            check_listen(tls.host, tls.port)
        if udp is not None:
            _check_pair("udp", udp)
        for state in self._buses:
            await self._open_at_start(state)
        loop = asyncio.get_running_loop()
        self.address = self.rtu_address = self.tls_address = self.udp_address = None

        def bound(server: asyncio.Server) -> tuple[str, int]:
            sock = server.sockets[0].getsockname()
            return str(sock[0]), int(sock[1])

        try:
            if port is not None:
                if self.engine_factory is not None:
                    engine = self.engine = self.engine_factory()
                    self._server = await loop.create_server(
                        lambda: EngineConnection(self, engine), host, port
                    )
                else:
                    self._server = await loop.create_server(lambda: _Connection(self), host, port)
                self.address = bound(self._server)
            if rtu is not None:
                self._rtu_server = await loop.create_server(lambda: _RtuConnection(self), *rtu)
                self.rtu_address = bound(self._rtu_server)
            if tls is not None:
                context = tls.context
                self._tls_server = await loop.create_server(
                    lambda: _TlsConnection(self, context), tls.host, tls.port
                )
                self.tls_address = bound(self._tls_server)
            if udp is not None:
                transport, self._udp = await loop.create_datagram_endpoint(
                    lambda: UdpListener(self), local_addr=udp
                )
                sock = transport.get_extra_info("sockname")
                self.udp_address = (str(sock[0]), int(sock[1]))
        except BaseException:  # no listener left behind half-started
            for half in self._listeners():
                half.close()
                await half.wait_closed()
            # (the addresses bound stay: which is None says which listener failed)
            self._server = self._rtu_server = self._tls_server = self._udp = None
            if self.engine is not None:
                self.engine.close()
                self.engine = None
            raise
        if self.policy is None:
            for where in (self.address, self.rtu_address, self.tls_address, self.udp_address):
                if where is not None and beyond_loopback(where[0]):
                    log.warning(
                        "listening on %s:%d beyond loopback with no access policy: any "
                        "client that reaches it may write (give a policy, or read-only)",
                        *where,
                    )
                    break
        self._running = True
        for state in self._buses:
            state.task = self._supervise(
                f"pyrtu-gateway-bus-{state.index}", partial(self._worker, state), state
            )
        lim = self.limits
        timeouts = [t for t in (lim.header_timeout, lim.idle_timeout) if t > 0]
        if timeouts:  # checked a few times per the shorter timeout
            interval = min(1.0, max(0.01, min(timeouts) / 4))
            self._sweeper = self._supervise(
                "pyrtu-gateway-sweeper", partial(self._sweep_every, interval)
            )
        return self

    def _supervise(
        self, name: str, body: Callable[[], Awaitable[None]], state: _BusState | None = None
    ) -> asyncio.Task[None]:
        return supervise(
            name,
            body,
            partial(self._task_failed, state),
            backoff=self.limits.backoff,
            running=lambda: self._running,
        )

    def _task_failed(self, state: _BusState | None, failure: TaskFailure) -> None:
        """A background task raised: count it; the first failure of a run is logged
        with its cause (the trace at debug level) and handed to ``on_task``; the
        request a bus worker was serving is answered 0x0B."""
        self.counters["task_failures"] += 1
        log.debug("task %s failed", failure.task, exc_info=failure.error)
        if failure.first:
            where = "" if state is None else f" (bus {state.name})"
            log.error(
                "task %s%s failed: %s (restarting in %.2f s)",
                failure.task,
                where,
                failure.cause,
                failure.retry_in,
            )
            if self.on_task is not None:
                try:
                    self.on_task(failure)
                except Exception:  # the hook's bug: the gateway goes on
                    log.exception("the on_task hook failed")
        if state is None:
            return
        state.waiter = None
        job, state.current = state.current, None
        conn = None if job is None else self._connections.get(job.conn)
        if job is None or conn is None:
            return
        conn.live.answered(time.monotonic())
        if job.slave != 0:
            try:
                self._answer(conn, job.transaction, job.unit, self._target_failed(job))
            except Exception:
                log.exception("connection %d: answering after the failure failed", conn.id)

    def _listeners(self) -> list[asyncio.Server | UdpListener]:
        """The listeners started (each has ``close``, ``wait_closed``, ``is_serving``)."""
        found = (self._server, self._rtu_server, self._tls_server, self._udp)
        return [listener for listener in found if listener is not None]

    async def close(self) -> None:
        self._running = False
        listeners = self._listeners()
        for server in listeners:
            server.close()
        for conn in list(self._connections.values()):
            conn.close()
        if self.engine is not None:
            self.engine.close()
            self.engine = None
        tasks = [s.task for s in self._buses if s.task is not None]
        if self._sweeper is not None:
            tasks.append(self._sweeper)
        for task in tasks:
            await _cancelled(task)
        for server in listeners:
            await server.wait_closed()
        self._server = self._rtu_server = self._tls_server = self._udp = self._sweeper = None
        for state in self._buses:
            state.task = None

    async def __aenter__(self) -> Gateway:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def stats(self) -> dict[str, object]:
        """Counters, open connections, queue lengths and bus occupancy."""
        stats: dict[str, object] = {
            **self.counters,
            "open_connections": len(self._connections),
            "queued": [len(s.queue) for s in self._buses],
            "bus_transactions": [s.transactions for s in self._buses],
            "bus_busy_seconds": [round(s.busy_seconds, 6) for s in self._buses],
            "bus_down": [s.reconnect.down for s in self._buses],
            "bus_outages": [s.reconnect.outages for s in self._buses],
            "denied_by": dict(self.denied_by),
            "unsent_bytes": sum(c.unsent() for c in self._connections.values()),
        }
        if self.engine is not None:
            self.engine.count_on_line()
            self.engine.merge(stats)
        return stats

    def bus_names(self) -> list[str]:
        """The buses' names, in the order of `stats`' per-bus lists."""
        return [s.name for s in self._buses]

    def health(self) -> list[str]:
        """What keeps the gateway from serving, one line each (empty: its listeners
        listen, its tasks run and every bus is up)."""
        if not self._running:
            return ["the gateway is not running"]
        problems = []
        for flag, server in (
            ("listener", self._server),
            ("RTU listener", self._rtu_server),
            ("TLS listener", self._tls_server),
            ("UDP listener", self._udp),
        ):
            if server is not None and not server.is_serving():
                problems.append(f"the {flag} is closed")
        tasks = [(f"bus {s.name}", s.task) for s in self._buses]
        if self._sweeper is not None:
            tasks.append(("the sweeper", self._sweeper))
        for what, task in tasks:
            if task is None or task.done():
                problems.append(f"{what}: its task is not running")
        for state in self._buses:
            outage = state.reconnect.outage
            if state.reconnect.down and outage is not None:
                problems.append(f"bus {state.name} down: {outage.error}")
        return problems

    # ---------------------------------------------------------- connections

    def _opened(self, conn: _Connection) -> None:
        if len(self._connections) >= self.limits.max_connections and not self._evict():
            self.counters["refused"] += 1
            log.info("connection refused: %d open", len(self._connections))
            conn.refuse()
            return
        self._next_id += 1
        conn.id = self._next_id
        self._connections[conn.id] = conn
        self.counters["connections"] += 1

    def _evict(self) -> bool:
        """Make room for a newcomer in the full table (`pick_victim`); False if every
        connection has work in progress."""
        if self.engine is not None:
            self.engine.refresh()
        victim_id = pick_victim((c.id, c.live, c.unsent() > 0) for c in self._connections.values())
        if victim_id is None:
            return False
        victim = self._connections[victim_id]
        self.counters["evicted"] += 1
        idle = time.monotonic() - victim.live.idle_since()
        what = "no request yet" if victim.live.last_active is None else "idle"
        log.info("connection %d (%s, %.1f s) gives way to a new one", victim.id, what, idle)
        victim.close()
        return True

    async def _sweep_every(self, interval: float) -> None:
        while True:
            await asyncio.sleep(interval)
            self._sweep(time.monotonic())

    def _sweep(self, now: float) -> None:
        """Close the connections whose header or idle timeout has passed."""
        lim = self.limits
        if self.engine is not None:
            self.engine.refresh()
            self.engine.count_on_line()
            self.engine.defer_if_needed()
        for conn in list(self._connections.values()):
            why = conn.live.expired(now, lim.header_timeout, lim.idle_timeout)
            if why is None:
                continue
            if why == HEADER:
                self.counters["header_timeouts"] += 1
                log.info(
                    "connection %d: a request unfinished after %s s: closed",
                    conn.id,
                    lim.header_timeout,
                )
            else:
                self.counters["idle_timeouts"] += 1
                log.info("connection %d: idle for %s s: closed", conn.id, lim.idle_timeout)
            conn.close()

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
        if self.policy is not None:
            decision = self.policy.decide(conn.identity, unit, pdu)
            if not decision.allowed:
                self._deny(conn, decision)
                self._answer(conn, transaction, unit, exception_pdu(pdu[0], ILLEGAL_FUNCTION))
                return
        route = self.routes.route(unit)
        if route is None:
            if unit == 0:
                counters["broadcasts"] += 1
                now = time.monotonic()
                for state in self._buses:
                    if not state.refuses(now):
                        self._submit(
                            state, Job(conn.id, transaction, 0, 0, pdu, conn.identity), conn
                        )
                return
            counters["no_route"] += 1
            self._answer(conn, transaction, unit, exception_pdu(pdu[0], GATEWAY_PATH_UNAVAILABLE))
            return
        state = self._buses[route[0]]
        if state.reconnect.down and state.refuses(time.monotonic()):
            counters["bus_unavailable"] += 1
            self._answer(conn, transaction, unit, exception_pdu(pdu[0], GATEWAY_PATH_UNAVAILABLE))
            return
        self._submit(state, Job(conn.id, transaction, unit, route[1], pdu, conn.identity), conn)

    def _tls_failed(self, conn: _Connection, reason: str) -> None:
        """A TLS connection failed (its handshake, or a record after it: a
        renegotiation asked for, an oversized record; it closes): counted, logged
        (and handed to ``on_denied`` as kind ``tls_handshake``) once per client and
        reason (``reason``: "TLS handshake: ..." or "TLS: ...")."""
        self.counters["tls_failures"] += 1
        self._say_refused(conn, Decision(False, "tls_handshake", reason))

    def _deny(self, conn: _Connection, decision: Decision) -> None:
        """A request the policy refuses (answered exception 01 by the caller): counted
        by kind, logged (and handed to ``on_denied``) once per client and reason."""
        self.counters["denied"] += 1
        self.denied_by[decision.kind] = self.denied_by.get(decision.kind, 0) + 1
        self._say_refused(conn, decision)

    def _say_refused(self, conn: _Connection, decision: Decision) -> None:
        who = conn.identity
        key = (who.address, who.role, decision.reason)
        if key in self._denials_logged:
            return
        if len(self._denials_logged) >= DENIALS_REMEMBERED:
            self._denials_logged.clear()  # bounded: an old pair may be logged again
        self._denials_logged.add(key)
        log.warning(
            "connection %d from %s: refused%s: %s",
            conn.id,
            who.describe(),
            "" if decision.kind == "tls_handshake" else " (exception 01)",
            decision.reason,
        )
        if self.on_denied is not None:
            try:
                self.on_denied(who, decision)
            except Exception:  # the hook's bug: the gateway goes on
                log.exception("the on_denied hook failed")

    def _audit(self, job: Job, answer: bytes | None) -> None:
        """Record an executed write in the audit trail (a failure to write it is
        logged and counted, never a reason to stop serving)."""
        trail = self.audit
        if trail is None or is_read(job.pdu):
            return
        who = job.who or Identity("?")
        try:
            trail.record(who, job.unit, job.pdu, answer, time.time())
        except (OSError, ValueError) as exc:
            self.counters["audit_failures"] += 1
            if self.counters["audit_failures"] == 1:
                log.error("the audit trail %s cannot be written: %s", trail.name, exc)
            return
        self.counters["audited_writes"] += 1

    def _submit(self, state: _BusState, job: Job, conn: _Connection) -> None:
        if state.now is not None and state.waiter is not None and not state.queue:
            # an idle bus whose transaction is a call: served here, in the order it
            # came (nothing is queued or under way before it)
            conn.live.outstanding += 1
            started = time.monotonic()
            try:
                answer = state.now(job.slave, job.pdu)
            except Exception as exc:
                self._finish(state, job, self._failed(state, job, exc), False, started)
            else:
                self._finish(state, job, *self._settle(state, job, answer), started)
            return
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
        conn.live.outstanding += 1
        state.wake()

    def _answer(self, conn: _Connection, transaction: int, unit: int, pdu: bytes) -> None:
        if pdu[0] & 0x80:
            self.counters["exceptions"] += 1
        else:
            self.counters["answers"] += 1
        conn.send(transaction, unit, pdu)

    # ---------------------------------------------------------------- buses

    async def _worker(self, state: _BusState) -> None:
        """One transaction at a time on the bus; a bus's errors are answered, not
        raised (anything else that raises is the supervisor's: `_task_failed`)."""
        loop = asyncio.get_running_loop()
        queue = state.queue
        connections = self._connections
        monotonic = time.monotonic
        # the answer PDU, an exception answer as its bytes (see GatewayBus)
        send = getattr(state.bus, "exchange", None) or state.bus.request
        while self._running:  # (not only the cancel: one can be lost under it, `_cancelled`)
            if state.reopen is not None and state.reconnect.down:
                await self._reopen(state)
                continue
            job = queue.pop()
            if job is None:
                state.waiter = waiter = loop.create_future()
                await waiter
                continue
            if job.conn not in connections:
                continue
            state.current = job
            started = monotonic()
            try:
                answer = await send(job.slave, job.pdu)
            except Exception as exc:  # (CancelledError is no Exception: it ends the worker)
                self._finish(state, job, self._failed(state, job, exc), False, started)
            else:
                self._finish(state, job, *self._settle(state, job, answer), started)

    def _settle(
        self, state: _BusState, job: Job, answer: bytes | None
    ) -> tuple[bytes | None, bool]:
        """A transaction's answer as the client gets it, and whether the bus answered."""
        answered = bool(answer) and job.slave != 0
        if state.reconnect.down:  # a request let through while down worked
            self._recovered(state)
        if job.slave == 0:
            return None, answered  # a broadcast: nothing to answer
        if not answer:  # the bus got no answer (a local application's silence)
            return self._target_failed(job), answered
        return answer, answered

    def _finish(
        self, state: _BusState, job: Job, answer: bytes | None, answered: bool, started: float
    ) -> None:
        """After a transaction: audited, counted, its answer written to its client."""
        self._audit(job, answer)
        now = time.monotonic()
        state.transactions += 1
        state.busy_seconds += now - started
        if answered and self.on_latency is not None:
            self.on_latency(state.name, job.slave, now - started)
        state.current = None  # from here its answer is being written
        conn = self._connections.get(job.conn)
        if conn is None:
            if answer is not None:
                self.counters["answers_dropped"] += 1
            return
        conn.live.answered(now)
        if answer is not None:
            self._answer(conn, job.transaction, job.unit, answer)

    async def _open_at_start(self, state: _BusState) -> None:
        """Open a `ReopeningBus` not opened yet.  A port that is not there (or a TCP
        peer that refuses) is a failed port as at run time: reported once, its
        requests answered 0x0A, reopened by the worker on the back-off schedule."""
        bus = state.bus
        if not isinstance(bus, ReopeningBus) or bus.is_open:
            return
        try:
            await bus.open()
        except (PortError, OSError) as exc:
            error = exc if isinstance(exc, PortError) else PortError(state.name, str(exc))
            self._port_failed(state, error, starting=True)

    async def _reopen(self, state: _BusState) -> None:
        """One attempt to reopen a failed bus, when the back-off says it is due."""
        rc = state.reconnect
        await asyncio.sleep(rc.wait(time.monotonic()))
        reopen = state.reopen
        assert callable(reopen)
        try:
            await reopen()
        except (PortError, OSError) as exc:
            rc.failed(time.monotonic(), exc)
            log.debug("bus %s: still unavailable: %s", state.name, exc)
        else:
            self._recovered(state)

    def _recovered(self, state: _BusState) -> None:
        outage = state.reconnect.recovered(time.monotonic())
        self.counters["bus_recoveries"] += 1
        if outage is not None:
            seconds = outage.duration or 0.0
            log.warning(
                "bus %s is back after %.1f s (%d attempts)", state.name, seconds, outage.attempts
            )
            self._event(
                BusEvent(state.index, state.name, True, outage.error, outage.attempts, seconds)
            )

    def _event(self, event: BusEvent) -> None:
        if self.on_bus is not None:
            try:
                self.on_bus(event)
            except Exception:  # the hook's bug: the bus goes on
                log.exception("the on_bus hook failed")

    def _port_failed(self, state: _BusState, exc: PortError, starting: bool = False) -> None:
        """The bus's port failed (``starting``: could not be opened at the start):
        report once per outage, answer what waits for it."""
        if state.reconnect.failed(time.monotonic(), exc):
            self.counters["bus_failures"] += 1
            log.warning(
                "bus %s %s: %s; its requests get exception 0x0A until it is back (retrying)",
                state.name,
                "is not available" if starting else "failed",
                exc,
            )
            self._event(BusEvent(state.index, state.name, False, str(exc), starting=starting))
        now = time.monotonic()
        while (job := state.queue.pop()) is not None:  # they would only fail in turn
            conn = self._connections.get(job.conn)
            if conn is None:
                continue
            conn.live.answered(now)
            if job.slave != 0:
                self.counters["bus_unavailable"] += 1
                self._answer(
                    conn,
                    job.transaction,
                    job.unit,
                    exception_pdu(job.pdu[0], GATEWAY_PATH_UNAVAILABLE),
                )

    def _failed(self, state: _BusState, job: Job, exc: Exception) -> bytes | None:
        """The gateway's answer when the bus's request raised ``exc`` (None for a
        broadcast): 0x0B when the device did not answer (within the timeout, after the
        retries, or not validly), 0x0A when the bus is unavailable.  (The device's
        exception answers are no exceptions: the bus's ``exchange`` returns them.)"""
        function = job.pdu[0]
        if isinstance(exc, PortError):
            self._port_failed(state, exc)
            if job.slave == 0:
                return None
            self.counters["bus_unavailable"] += 1
            return exception_pdu(function, GATEWAY_PATH_UNAVAILABLE)
        if isinstance(exc, (ModbusError, ValueError, RuntimeError)):
            # no answer, a garbled answer after the retries, or a request the bus refuses
            if not isinstance(exc, NoResponseError):
                log.info("unit %d: %s", job.unit, exc)
        else:  # a bus's bug: the bus goes on, the client gets an answer, the log the trace
            log.error("unit %d: the bus failed", job.unit, exc_info=exc)
        return None if job.slave == 0 else self._target_failed(job)

    def _target_failed(self, job: Job) -> bytes:
        """Exception 0x0B, gateway target device failed to respond ([AP] 7)."""
        self.counters["timeouts"] += 1
        return exception_pdu(job.pdu[0], GATEWAY_TARGET_FAILED)
