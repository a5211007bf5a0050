"""A Modbus TCP server for a slave application: `pyrtu.Slave`, `pyrtu.drivers.aio.AsyncSlave`,
the device simulators; the same DataStore and handlers as on the serial line.

Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: the server answers with the
request's transaction id, protocol id and unit id.  The unit ids served are the
slave's addresses, plus 0xFF and 0 for its lowest address: a client addresses a
TCP device directly with 0xFF, and "the value 0 is also accepted to communicate
directly to a MODBUS/TCP device" (4.4.1.2; libmodbus's unit-test-client expects an
answer to unit 0).  So on TCP, unit 0 is not a broadcast: it is executed by the
lowest address and answered.  Any other unit id gets exception 0x0A (gateway path
unavailable).

``await server.start(host, port, udp=(host, port))`` also serves Modbus over UDP
(one MBAP ADU per datagram, as pymodbus's ``ModbusUdpServer``), with the same policy,
audit trail and queue; ``port=None`` serves UDP only.

It is the gateway's machinery (`pyrtu.gateway`) with the application in place of
a serial bus: many connections, each read by an `MbapFramer` (a bad header closes
that connection only), requests executed one at a time through the fair queue,
the same limits::

    store = pyrtu.DataStore()
    store.holding_registers.add_range(0, [0] * 100)
    server = TcpServer.for_store(1, store)       # a slave on TCP only
    server = TcpServer(slave)                    # or a Slave/AsyncSlave that also serves serial
    async with await server.start("127.0.0.1", 5020):
        await asyncio.Event().wait()

A `pyrtu.Slave` served on both its serial port and TCP sees one DataStore; its
execution step runs under the slave's lock (the serial side runs in its thread).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from pyrtu.core._closing import AsyncClosing
from pyrtu.core.line import LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.drivers.supervise import TaskFailure
from pyrtu.gateway._engine import ServerEngine, eligible
from pyrtu.gateway._plan import check_listen
from pyrtu.gateway.gateway import Gateway, GatewayLimits
from pyrtu.protocol.datastore import DataStore
from pyrtu.protocol.server import Application
from pyrtu.security.audit import AuditTrail
from pyrtu.security.policy import Decision, Identity, Policy
from pyrtu.security.tls import TlsListen

UNIT_SELF = 0xFF
#: unit 0 on TCP: the device itself too ([TCP] 4.4.1.2)
UNIT_DIRECT = 0


def _check_address(address: object) -> None:
    if isinstance(address, (str, bytes)) or not isinstance(address, (int, Iterable)):
        raise TypeError(f"address must be a slave address or an iterable of them, not {address!r}")
    items = [address] if isinstance(address, int) else list(address)
    for a in items:
        if isinstance(a, bool) or not isinstance(a, int):
            raise TypeError(f"address: a slave address is an integer 1..247, not {a!r}")
        if not 1 <= a <= 247:
            raise ValueError(f"address: a slave address is 1..247, not {a}")
    if not items:
        raise ValueError("address: a slave needs at least one address")


def _check_store(store: object) -> None:
    if store is None or isinstance(store, DataStore):
        return
    if isinstance(store, Mapping):
        for address, each in store.items():
            if isinstance(address, bool) or not isinstance(address, int):
                raise TypeError(f"store: the keys are slave addresses, not {address!r}")
            if not isinstance(each, DataStore):
                raise TypeError(f"store[{address}] must be a DataStore, not {type(each).__name__}")
        return
    raise TypeError(
        f"store must be a DataStore or a mapping address -> DataStore, not {type(store).__name__}"
    )


class LocalBus:
    """An application in place of a serial bus: `execute` is the transaction (the
    application guards it: `SlaveBase.execute` takes the sync Slave's lock)."""

    def __init__(self, app: Application) -> None:
        self.app = app

    def transact_now(self, slave: int, pdu: bytes) -> bytes | None:
        """The answer PDU (an exception answer too, as bytes); None: no answer (a
        broadcast, listen-only mode, a handler that stays silent).  A plain call: the
        gateway runs it in the request's callback while the bus is idle."""
        response = self.app.execute(slave, pdu)
        return None if slave == 0 else response

    async def request(self, slave: int, pdu: bytes) -> bytes | None:
        """`transact_now`, awaited (the gateway's worker, for a request queued behind
        others)."""
        return self.transact_now(slave, pdu)


class TcpServer(AsyncClosing):
    """Serves ``app`` over Modbus TCP (see the module docstring); ``on_task``: as
    `Gateway`'s (a background task that raised, restarted on the back-off);
    ``policy``, ``audit``, ``on_denied``: as `Gateway`'s (the access policy of
    `pyrtu.security`, exception 01 for a request outside it; the audit trail of
    executed writes).

    ``engine`` (default True): on the C core (Linux), a `pyrtu.Slave`'s reads on the
    Modbus TCP listener are answered by a C thread from a copy of its DataStore,
    without Python per request (`pyrtu.gateway._engine`); everything else is
    executed as before.  ``engine_refused`` says why a server runs without it."""

    def __init__(
        self,
        app: Application,
        limits: GatewayLimits | None = None,
        on_task: Callable[[TaskFailure], None] | None = None,
        *,
        policy: Policy | None = None,
        audit: AuditTrail | None = None,
        on_denied: Callable[[Identity, Decision], None] | None = None,
        engine: bool = True,
    ) -> None:
        if not callable(getattr(app, "execute", None)) or not getattr(app, "addresses", None):
            raise TypeError(
                f"app must have execute(unit, pdu) and addresses, not {type(app).__name__}"
            )
        if not isinstance(engine, bool):
            raise TypeError(f"engine must be True or False, not {engine!r}")
        self.app = app
        units = {a: a for a in app.addresses}
        units[UNIT_SELF] = units[UNIT_DIRECT] = min(app.addresses)
        self._gateway = Gateway(
            [(LocalBus(app), units)],
            limits,
            on_task=on_task,
            policy=policy,
            audit=audit,
            on_denied=on_denied,
        )
        #: why the C engine does not serve this app (None: it does, on the C core)
        self.engine_refused: str | None = eligible(app) if engine else "engine=False"
        if self.engine_refused is None:
            assert isinstance(app, SlaveBase)
            gateway = self._gateway
            gateway.engine_factory = lambda: ServerEngine(gateway, app, units)

    @classmethod
    def for_store(
        cls,
        address: int | Iterable[int] = 1,
        store: DataStore | Mapping[int, DataStore] | None = None,
        limits: GatewayLimits | None = None,
        *,
        policy: Policy | None = None,
        audit: AuditTrail | None = None,
        on_denied: Callable[[Identity, Decision], None] | None = None,
        engine: bool = True,
        **options: Any,
    ) -> TcpServer:
        """A slave on TCP only: the standard functions over ``store`` (``options``: the
        `pyrtu.Slave` keywords functions, identification, server_id, ...; ``policy``,
        ``audit``, ``on_denied`` and ``engine`` as in the constructor).
        TypeError/ValueError naming ``address`` or ``store`` when they are wrong."""
        _check_address(address)
        _check_store(store)
        app = SlaveBase(address, store, line=LineConfig(), **options)
        return cls(app, limits, policy=policy, audit=audit, on_denied=on_denied, engine=engine)

    @property
    def address(self) -> tuple[str, int] | None:
        """The (host, port) bound, once started."""
        return self._gateway.address

    @property
    def counters(self) -> dict[str, int]:
        counters = dict(self._gateway.counters)
        engine = self._gateway.engine
        if engine is not None:
            engine.merge(counters)
        return counters

    def stats(self) -> dict[str, object]:
        """The gateway's `Gateway.stats`: counters, open connections (on the loop)."""
        return self._gateway.stats()

    def health(self) -> list[str]:
        """What keeps the server from serving (empty: it listens, its tasks run)."""
        return self._gateway.health()

    @property
    def tls_address(self) -> tuple[str, int] | None:
        """The (host, port) of the TLS listener, once started with ``tls``."""
        return self._gateway.tls_address

    @property
    def udp_address(self) -> tuple[str, int] | None:
        """The (host, port) of the UDP listener, once started with ``udp``."""
        return self._gateway.udp_address

    async def start(
        self,
        host: str = "127.0.0.1",
        port: int | None = 502,
        tls: TlsListen | None = None,
        udp: tuple[str, int] | None = None,
    ) -> TcpServer:
        """Listen on host:port (0: any free port, see ``address``) and, with ``tls``
        (`pyrtu.security.tls.TlsListen`: where, and `server_context`), for Modbus/TCP
        Security (``tls_address``), with ``udp=(host, port)`` for Modbus over UDP
        (``udp_address``: one ADU per datagram, the client's address its identity for
        the policy; `pyrtu.gateway._udp`); ``port=None``: UDP (or TLS) only.
        RuntimeError if it already listens (close it first); TypeError/ValueError
        naming ``host``, ``port`` or ``udp`` before anything is bound."""
        if port is not None:
            check_listen(host, port)
        await self._gateway.start(host, port, tls=tls, udp=udp)
        return self

    async def serve_forever(
        self, host: str = "127.0.0.1", port: int | None = 502, udp: tuple[str, int] | None = None
    ) -> None:
        """`start` (``udp`` as there), then serve until cancelled, then `close`."""
        await self.start(host, port, udp=udp)
        try:
            await asyncio.Event().wait()
        finally:
            await self.close()

    async def close(self) -> None:
        await self._gateway.close()

    def __repr__(self) -> str:
        return f"TcpServer({self.app!r}, address={self.address})"


__all__ = ["UNIT_DIRECT", "UNIT_SELF", "Application", "LocalBus", "TcpServer"]
