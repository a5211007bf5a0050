"""The C engine of `pyrtu.tcp.server.TcpServer`: plain reads answered without Python.

csrc/rtu_serve_io.c runs a thread that reads the connections of the servers'
Modbus TCP listeners, frames their requests and answers the reads (FC 01-04) that
their `pyrtu.protocol._image.StoreImage` holds, with the GIL released; every other
request (a write, another function, an address outside the ranges, a range with
an ``on_read`` callback, a quantity out of bounds: any exception answer) is handed
to the event loop as an event, executed there by the gateway as before
(`Gateway._request`), and its answer given back to the engine, which keeps each
connection's answers in request order (it reads none of that connection's further
requests meanwhile).

One `Engine` (one thread) serves every `TcpServer` of an event loop: each server's
`ServerEngine` keeps its routes (unit id -> image), its connections and its
figures; a connection carries its server's routes into the engine.  The engine has
`CAPACITY` connections; a connection past them is served by Python, as without an
engine.

The gateway keeps what it keeps for every connection: the table and its limits
(accept, eviction, header and idle timeouts: a connection's liveness is read from
the engine before each sweep and eviction), its counters (the engine's answers are
added to ``requests`` and ``answers``, and to the bus's transactions, when they
are read), the slave's event counter (FC 11: brought up to date before any request
is executed in Python), closing and resets.  A server's connections hand every
request to Python while its slave is in listen-only mode or has ``on_request``
hooks, while its gateway has a policy, an audit trail or a latency observer
(``--metrics``), or while the gateway's logger is at DEBUG (every frame logged).

`EngineConnection` is the listener's protocol: accepted by asyncio as any
connection, then, on the loop's next turn, its reading paused and a duplicate of
its socket handed to the engine (bytes asyncio read before that, part of a
request, keep the connection on the Python path); asyncio's transport stays for
closing it.  An engine's memory lives while its thread runs (`Engine._running`):
a server left open when its loop ends is stopped when the next engine starts.

A connection accepted while its server hands everything to Python (a drive
simulator's ``on_request`` hook, that runs its model at every telegram, or a
policy) is served by asyncio alone, as without an engine: the engine would only
add a hop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import threading
import weakref
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Protocol

from pyrtu.core import _backend
from pyrtu.core.mbap import MBAP_HEADER
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.protocol._image import StoreImage, available
from pyrtu.security.audit import AuditTrail
from pyrtu.security.policy import Policy

from ._conn import Owner, _Connection, _reset


class EngineOwner(Owner, Protocol):
    """What the engine asks of the gateway (`pyrtu.gateway.gateway.Gateway`)."""

    policy: Policy | None
    audit: AuditTrail | None
    on_latency: Callable[[str, int, float], None] | None


log = logging.getLogger("pyrtu.gateway")

#: the functions the engine answers: [AP] 6.1-6.4, the reads of the four tables
READS = (1, 2, 3, 4)
#: connections one engine serves (more are served by Python)
CAPACITY = 1024


def eligible(app: object) -> str | None:
    """Why ``app`` cannot be served by the engine (None: it can): the engine answers
    a `SlaveBase`'s own reads on the C core only."""
    if not available():
        return "the C core has no engine here"
    if not isinstance(app, SlaveBase):
        return "not a pyrtu slave"
    if app._backend is not _backend.C:
        return "the slave runs on the pure-Python backend"
    builtins = app._builtins()
    for fc in READS:
        if fc not in app.functions or app._handlers.get(fc) is None:
            return f"function {fc} is not served"
        if getattr(app._handlers[fc], "__func__", None) is not getattr(
            builtins[fc], "__func__", None
        ):
            return f"function {fc} is the application's own"
    return None


class Engine:
    """One rtu_serve thread for the TcpServers of an event loop (`of`)."""

    _by_loop: ClassVar[weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Engine]] = (
        weakref.WeakKeyDictionary()
    )
    #: every engine whose thread runs, held until `close` joins it: the thread works
    #: in the engine's memory (``_mem``), which must not be freed under it, as it
    #: would be when a loop ended with a server never closed goes
    _running: ClassVar[set[Engine]] = set()

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> Engine:
        """``loop``'s engine, started at the first call (again after it stopped);
        the engines of loops closed meanwhile are stopped first (`reap`)."""
        cls.reap()
        engine = cls._by_loop.get(loop)
        if engine is None or engine.closed:
            engine = cls._by_loop[loop] = cls(loop, CAPACITY)
        return engine

    @classmethod
    def reap(cls) -> None:
        """Stop every engine whose event loop was closed with a server still on it
        (never closed: its thread and its clients' connections would stay for the
        process's life)."""
        for engine in [e for e in cls._running if e._loop.is_closed()]:
            log.warning(
                "a TCP server's engine outlived its event loop (a server never closed):"
                " stopped, %d connection(s) closed",
                len(engine._conns),
            )
            for conn in engine._conns.values():  # (their transports cannot close them)
                conn.shut()
            engine.close()

    def __init__(self, loop: asyncio.AbstractEventLoop, capacity: int) -> None:
        c = _backend.C
        assert c is not None
        self._ffi, self._lib = ffi, lib = c.ffi, c.lib
        self.capacity = capacity
        self._mem = ffi.new("char[]", lib.rtu_serve_size(capacity))
        self._s = ffi.cast("rtu_serve *", self._mem)
        # past this many answer bytes the socket did not take (the kernel's buffer full
        # too), the client does not read its answers: the gateway's ``slow_clients``
        unsent = max(1, int(lib.RTU_SERVE_OUT_CAP) // 2)
        if lib.rtu_serve_init(self._s, capacity, unsent) != 0:
            err = lib.rtu_serve_errno(self._s)
            raise OSError(err, f"the TCP server's engine cannot start: {os.strerror(err)}")
        self._events = ffi.new("rtu_serve_event[]", 2 * capacity)
        self._state = ffi.new("rtu_serve_conn_state *")
        self._free = list(range(capacity - 1, -1, -1))
        self._conns: dict[int, EngineConnection] = {}
        self._loop = loop
        self.closed = False
        #: the `ServerEngine`s on it: the thread stops when the last one closes
        self.users = 0
        Engine._running.add(self)
        loop.add_reader(lib.rtu_serve_fd(self._s), self._ready)

    def release(self) -> None:
        """A `ServerEngine` closed: the last one stops the thread (`of` starts
        another for the next server)."""
        self.users -= 1
        if self.users <= 0:
            self.close()

    def attach(self, conn: EngineConnection, fd: int, routes: Any, defer: bool) -> int | None:
        """Hand ``fd`` (the engine owns it from now on) to the engine: its slot, or
        None when every slot is taken (``fd`` is closed then)."""
        if self.closed or not self._free:
            os.close(fd)
            return None
        slot = self._free.pop()
        if self._lib.rtu_serve_attach(self._s, slot, fd, routes, int(defer)) != 0:
            self._free.append(slot)
            os.close(fd)
            return None
        self._conns[slot] = conn
        return slot

    def detach(self, slot: int) -> None:
        if self._conns.pop(slot, None) is None:
            return
        self._lib.rtu_serve_detach(self._s, slot)
        self._free.append(slot)

    def defer(self, slot: int, on: bool) -> None:
        self._lib.rtu_serve_defer(self._s, slot, int(on))

    def send(self, slot: int, adu: bytes) -> None:
        """The answer to the request the engine handed over for ``slot``."""
        self._lib.rtu_serve_send(self._s, slot, adu, len(adu))

    def state(self, slot: int) -> Any:
        """``slot``'s rtu_serve_conn_state (one shared record: read it at once)."""
        self._lib.rtu_serve_conn(self._s, slot, self._state)
        return self._state

    def _ready(self) -> None:
        """The engine's events: requests handed over, connections ended."""
        lib = self._lib
        n = lib.rtu_serve_take(self._s, self._events, 2 * self.capacity)
        for i in range(n):
            ev = self._events[i]
            conn = self._conns.get(ev.conn)
            if conn is not None and not conn.closed:
                conn.event(ev)

    def close(self) -> None:
        """Stop the thread (every connection detached first)."""
        if self.closed:
            return
        self.closed = True
        if Engine._by_loop.get(self._loop) is self:
            del Engine._by_loop[self._loop]  # (it names the loop: the loop may go)
        if not self._loop.is_closed():
            self._loop.remove_reader(self._lib.rtu_serve_fd(self._s))
        self._conns.clear()
        # the thread joined, every connection's descriptor closed: the memory may go
        self._lib.rtu_serve_destroy(self._s)
        Engine._running.discard(self)


class ServerEngine:
    """A `TcpServer`'s part of its loop's `Engine`: the routes its connections carry
    (unit id -> the image of the slave it reaches), its connections, its figures."""

    def __init__(
        self,
        owner: EngineOwner,
        app: SlaveBase,
        units: Mapping[int, int],
    ) -> None:
        c = _backend.C
        assert c is not None
        ffi = c.ffi
        self.owner = owner
        self.app = app
        #: what the engine answered on this server's connections, by function too
        #: (`sync`; from any thread: under ``_figures``)
        self.answered = 0
        self.by_function = [0] * 5
        self._figures = threading.RLock()
        self._on_line = [0] * 5  # (of by_function: counted in the slave's event counter)
        self.engine = Engine.of(asyncio.get_running_loop())
        self.engine.users += 1
        self.closed = False
        #: the images, kept alive while a connection names them
        self._images = {slave: StoreImage.of(app.store_for(slave)) for slave in units.values()}
        self.routes = ffi.new("const rtu_image *[256]")
        for unit, slave in units.items():
            self.routes[unit] = self._images[slave].image
        self.conns: set[EngineConnection] = set()
        self.deferring = self._deferring()

    def _deferring(self) -> bool:
        app, owner = self.app, self.owner
        return bool(
            app.listen_only
            or app._hooks
            or owner.policy is not None
            or owner.audit is not None
            or owner.on_latency is not None
            or log.isEnabledFor(logging.DEBUG)
        )

    def defer_if_needed(self) -> None:
        """Every request of this server's connections to Python while the slave
        listens only, ... (the module docstring); the engine's answers again once
        none of that holds."""
        defer = self._deferring()
        if defer != self.deferring:
            self.deferring = defer
            for conn in self.conns:
                conn.defer(defer)

    def sync(self) -> None:
        """Bring ``answered`` and ``by_function`` up to date (any thread)."""
        with self._figures:
            for conn in list(self.conns):
                conn.sync()

    def merge(self, figures: dict[str, Any]) -> None:
        """Add what the engine answered to the gateway's ``figures`` (its counters or
        `Gateway.stats`): requests, answers, the bus's transactions (any thread)."""
        self.sync()
        answered = self.answered
        if "requests" in figures:
            figures["requests"] += answered
            figures["answers"] += answered
        if "bus_transactions" in figures:
            figures["bus_transactions"] = [figures["bus_transactions"][0] + answered]

    def count_on_line(self) -> None:
        """The slave's event counter (FC 11) brought up to date with the engine's
        answers (any thread; the loop's before it executes a request)."""
        with self._figures:
            self.sync()
            line = self.app.line
            for fc in READS:
                n = self.by_function[fc] - self._on_line[fc]
                if n:
                    self._on_line[fc] += n
                    line.completed(fc, n)

    def refresh(self) -> None:
        """Every connection's liveness from the engine (before a sweep or eviction)."""
        for conn in self.conns:
            conn.refresh()

    def close(self) -> None:
        """The server stops (its connections closed by the gateway first)."""
        if self.closed:
            return
        self.closed = True
        for conn in list(self.conns):
            conn.close()
        self.engine.release()


class EngineConnection(_Connection):
    """A client of the plain listener, its socket read and written by the engine;
    asyncio's transport, paused, stays to close it (and serves it when the engine
    has no slot free)."""

    def __init__(self, gateway: EngineOwner, server: ServerEngine) -> None:
        super().__init__(gateway)
        self.server = server
        self.slot: int | None = None
        self._seen = 0
        self._seen_by_function = [0] * 5

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)  # (the gateway's table: it may refuse it)
        if not self.closed:
            # handed over on the next turn of the loop, not now: asyncio starts reading
            # a socket after connection_made, and some releases (Debian 12's 3.11.2)
            # do so even when the protocol paused it there (CPython gh-103607)
            asyncio.get_running_loop().call_soon(self._hand_over)

    def _hand_over(self) -> None:
        """Reading paused and a duplicate of the socket handed to the engine, unless
        asyncio read from it meanwhile what is not done with (part of a request, a
        request whose answer is still to come or still in asyncio's buffer: this
        protocol serves the connection, so that its answers keep their order), the
        server hands everything to Python, or the engine has no slot free."""
        transport = self.transport
        assert transport is not None  # (set by connection_made)
        if self.closed or self.buffered:
            return
        if self.live.outstanding or transport.get_write_buffer_size():
            return  # (not reached by a TcpServer's own slave, which answers at once)
        sock = transport.get_extra_info("socket")
        if sock is None:
            return  # (no socket to share: served by this protocol, as any connection)
        server = self.server
        server.defer_if_needed()
        if server.deferring or server.closed:
            return  # (every request would be Python's: served by this protocol, no hop)
        transport.pause_reading()
        self.slot = server.engine.attach(
            self, os.dup(sock.fileno()), server.routes, server.deferring
        )
        if self.slot is None:
            transport.resume_reading()  # (no slot: served by this protocol)
        else:
            server.conns.add(self)

    def event(self, ev: Any) -> None:
        """One event of the engine's for this connection."""
        lib = self.server.engine._lib
        gateway = self.server.owner
        kind = ev.kind
        if kind == lib.RTU_SERVE_REQUEST:
            adu = bytes(self.server.engine._ffi.buffer(ev.adu, ev.len))
            transaction, _, _, unit = MBAP_HEADER.unpack_from(adu)
            if log.isEnabledFor(logging.DEBUG):
                log.debug("connection %d: RX unit %d: %s", self.id, unit, adu.hex(" "))
            self.server.count_on_line()  # (FC 11's event counter, as it stands)
            try:
                gateway._request(self, transaction, unit, adu[7:])
            except Exception:  # (a fault of the gateway's: as asyncio's transport does
                # with a protocol's, this connection is closed, the others go on)
                log.exception("connection %d: the request failed: closed", self.id)
                self.close()
                return
            if not self.closed:
                self.live.data(ev.at * 1e-9, False, True)
        elif kind == lib.RTU_SERVE_CLOSED:
            self.close()
        elif kind == lib.RTU_SERVE_BAD_HEADER:
            gateway.counters["bad_headers"] += 1
            log.info("connection %d: bad MBAP header (error %d): closed", self.id, ev.err)
            self.close()
        else:  # RTU_SERVE_STALLED
            gateway.counters["slow_clients"] += 1
            log.info("connection %d does not read its answers: reset", self.id)
            self.reset()

    def send(self, transaction: int, unit: int, pdu: bytes) -> None:
        if self.slot is None:
            super().send(transaction, unit, pdu)
            return
        if self.closed:
            self.gateway.counters["answers_dropped"] += 1
            return
        adu = self.encode(transaction, unit, pdu)
        # (what the request just executed may stop the engine's own answers, as FC 08's
        # listen-only mode does: said before the engine reads the next request)
        self.server.defer_if_needed()
        self.server.engine.send(self.slot, adu)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("connection %d: TX unit %d: %s", self.id, unit, adu.hex(" "))

    def defer(self, on: bool) -> None:
        if self.slot is not None:
            self.server.engine.defer(self.slot, on)

    def sync(self) -> None:
        """What the engine answered on this connection since the last call, added to
        its server's figures (under the server's ``_figures`` lock)."""
        slot = self.slot
        if slot is None:
            return
        engine = self.server.engine
        st = engine._ffi.new("rtu_serve_conn_state *")  # (its own: any thread)
        if engine._lib.rtu_serve_conn(engine._s, slot, st) != 0:
            return  # (detached meanwhile: counted then)
        answered = int(st.answered) - self._seen
        if answered:
            self._seen += answered
            server = self.server
            server.answered += answered
            for fc in READS:
                n = int(st.by_function[fc]) - self._seen_by_function[fc]
                self._seen_by_function[fc] += n
                server.by_function[fc] += n

    def refresh(self) -> None:
        """The liveness the engine saw: its last complete request, the request it is
        receiving."""
        if self.slot is None:
            return
        st = self.server.engine.state(self.slot)
        live = self.live
        if st.last_request:
            last = st.last_request * 1e-9
            if live.last_active is None or last > live.last_active:
                live.last_active = last
        live.partial_since = st.partial_since * 1e-9 if st.partial_since else None

    def unsent(self) -> int:
        if self.slot is None:
            return super().unsent()
        st = self.server.engine.state(self.slot)
        # (a request handed over counts as an answer not yet written: work in progress)
        return int(st.unsent) + int(st.handed)

    def _detach(self) -> None:
        if self.slot is not None:
            server = self.server
            with server._figures:  # (its last figures, before the engine forgets them)
                self.sync()
                server.conns.discard(self)
                server.engine.detach(self.slot)
                self.slot = None

    def close(self) -> None:
        self._detach()
        super().close()

    def shut(self) -> None:
        """Its loop closed: the connection shut down at the socket (its peer sees it
        end; asyncio's transport, whose loop is gone, closes the descriptor when it
        goes)."""
        sock = None if self.transport is None else self.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        self.closed = True

    def reset(self) -> None:
        """Closed with a reset (the client does not read its answers)."""
        self._detach()
        t = self.transport
        if t is not None and not self.closed:
            self.closed = True
            _reset(t)


__all__ = ["CAPACITY", "Engine", "EngineConnection", "ServerEngine", "eligible"]
