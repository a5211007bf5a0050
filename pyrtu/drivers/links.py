"""A master's transport ("link"), as libmodbus has its ``modbus_backend_t``.

`pyrtu.Master` and `pyrtu.drivers.aio.AsyncMaster` are one class each whatever the port:
the port string picks the link object they drive from one table, `TRANSPORTS` (by
`scheme_of`; the masters hold no branch on the scheme): a serial line
(`pyrtu.drivers.master.SerialLink`: a device path, a pyserial object or URL;
`RtuOverTcpLink`: ``rtu+tcp://`` RTU frames over a socket), Modbus TCP
(``tcp://``, or in TLS ``mbaps://`` with a ``tls`` context: `pyrtu.tcp.link.TcpLink`
/ `AsyncTcpLink`) or Modbus over UDP (``udp://``: `pyrtu.tcp.udp.UdpLink` /
`AsyncUdpLink`), each imported only when such a port is opened, so ``import pyrtu``
loads neither TCP nor asyncio.

Adding a transport is one module with its link classes (a sync one for `Master`, an
asyncio one for `AsyncMaster`, each with ``open(port, line, options, max_in_flight)``,
answering `Link`; the asyncio one's ``transact``, ``connect`` and ``close`` are
coroutines; a static ``check_port(port)`` for a URL, so that a bad one is a usage
error before anything opens) and one `Transport` row naming them, with its scheme in
``PYRTU_SCHEMES``.  What the rest of pyrtu needs to know of a transport is in its
row, not in a branch on the scheme: whether it pipelines, takes TLS, its default
``t35``, whether it carries MBAP ADUs (unit ids 0..255 as on Modbus TCP, no wire
timing: the poller's `unit_problem` and `Wire`), so the poller, the bridge and
every command that takes ``--port`` open the new scheme with no other change.

A link answers for the master's properties (`Link`), maps the unit ids its
transport allows (``address``, see `pyrtu.pdu.requests.Steps`) and runs one
transaction: ``transact(call) -> (value, end_time)``, ``end_time`` being when the
answer's last byte came (monotonic seconds; now for a broadcast).

A link whose port or connection failed comes back on the one retry schedule
(`pyrtu.drivers.reconnect`) through a `LinkRevival`: a serial line reopens its port
(the same path and options), a TCP link reconnects.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

from pyrtu.core.rules import LengthRule
from pyrtu.core.timing import check_seconds
from pyrtu.drivers._portname import (
    MBAP_SCHEMES,
    MBAPS_SCHEME,
    PYRTU_SCHEMES,
    RTU_TCP_SCHEME,
    TCP_SCHEME,
    UDP_SCHEME,
    url_scheme,
)
from pyrtu.drivers.reconnect import Backoff, Reconnect
from pyrtu.pdu.errors import PortError
from pyrtu.pdu.requests import Call

#: the masters' logger
log = logging.getLogger("pyrtu.drivers.master")


def scheme_of(port: object) -> str | None:
    """``"tcp"``, ``"mbaps"``, ``"rtu+tcp"`` or ``"udp"`` for those URLs; None for a serial
    port (a path, a pyserial URL or object).  ValueError for a URL no one opens
    (`url_scheme`: ``quic://...: unsupported scheme quic://; supported: tcp://, ...``)."""
    scheme = url_scheme(port)
    return scheme if scheme in PYRTU_SCHEMES else None


def check_tls(transport: Transport, tls: object) -> Any:
    """``tls``: the `ssl.SSLContext` of an ``mbaps://`` port (required there, and
    nowhere else); ValueError/TypeError naming ``tls``."""
    if transport.tls:
        import ssl  # (only where TLS is asked for)

        if not isinstance(tls, ssl.SSLContext):
            raise (ValueError if tls is None else TypeError)(
                "tls: an mbaps:// port needs the client's TLS context, "
                "tls=pyrtu.security.tls.client_context(cert, key, ca)"
                + ("" if tls is None else f", not {type(tls).__name__}")
            )
    elif tls is not None:
        raise ValueError("tls: only an mbaps:// port takes a TLS context")
    return tls


def check_retries(retries: object) -> int:
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise ValueError(f"retries must be a non-negative integer, not {retries!r}")
    return retries


def check_in_flight(value: object, tcp: bool) -> int:
    """``max_in_flight``: requests on the wire at once; only an asyncio master on a
    transport that pipelines (`Transport.pipelines`: ``tcp://``...) keeps more than one."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"max_in_flight must be an integer, not {value!r}")
    if value < 1 or (value != 1 and not tcp):
        ports = " and ".join(f"{row.scheme}://" for row in TRANSPORTS.values() if row.pipelines)
        raise ValueError(
            f"max_in_flight must be 1 on a serial line, not {value} "
            f"(only {ports} ports keep several requests on the wire)"
        )
    return value


@dataclass(frozen=True)
class Transport:
    """One row of `TRANSPORTS`: what a port string's scheme opens.  ``sync`` and
    ``aio`` name the link classes of `pyrtu.Master` and `pyrtu.drivers.aio.AsyncMaster`
    (``"module:Class"``, imported when such a port is opened); each has
    ``open(port, line, options, max_in_flight)``."""

    scheme: str | None
    what: str
    sync: str
    aio: str
    #: whether an asyncio master keeps several requests on the wire (``max_in_flight``)
    pipelines: bool = False
    #: whether it takes a TLS context (``tls=``, required)
    tls: bool = False
    #: the inter-frame silence when ``t35`` is not given (None: the line's own)
    t35: float | None = None
    #: whether it carries MBAP ADUs: unit ids 0..255 (0: the device itself, 248..255:
    #: what is behind it), no wire timing (the poller's `Wire.tcp`), its asyncio link
    #: opening its socket at the first request (or ``connect``), not when made
    mbap: bool = False

    def link_class(self, asyncio: bool) -> Any:
        module, _, name = (self.aio if asyncio else self.sync).partition(":")
        return getattr(importlib.import_module(module), name)

    def check_port(self, port: object) -> None:
        """ValueError naming ``port`` when its link cannot open it (a URL without a
        host, a port outside 0..65535...), before anything is opened: what a
        configuration file or a command line says at once (the link's
        ``check_port``; a serial port has none: its open says what is wrong)."""
        check = getattr(self.link_class(False), "check_port", None)
        if check is not None:
            check(port)


_SERIAL = "pyrtu.drivers.master:SerialLink"
_RTU_TCP = "pyrtu.drivers.master:RtuOverTcpLink"
_TCP, _AIO_TCP = "pyrtu.tcp.link:TcpLink", "pyrtu.tcp.link:AsyncTcpLink"
_UDP, _AIO_UDP = "pyrtu.tcp.udp:UdpLink", "pyrtu.tcp.udp:AsyncUdpLink"
#: the transports, by the scheme of the port string (None: a serial port: a device
#: path, a pyserial object or a pyserial URL).  A new transport is a module with its
#: link classes and one row here (and its scheme in `PYRTU_SCHEMES`)
TRANSPORTS: dict[str | None, Transport] = {
    None: Transport(None, "a serial line, RTU or ASCII", _SERIAL, _SERIAL),
    RTU_TCP_SCHEME: Transport(RTU_TCP_SCHEME, "RTU frames over TCP", _RTU_TCP, _RTU_TCP, t35=0.0),
    TCP_SCHEME: Transport(TCP_SCHEME, "Modbus TCP", _TCP, _AIO_TCP, pipelines=True, mbap=True),
    MBAPS_SCHEME: Transport(
        MBAPS_SCHEME,
        "Modbus/TCP Security (TLS)",
        _TCP,
        _AIO_TCP,
        pipelines=True,
        tls=True,
        mbap=True,
    ),
    UDP_SCHEME: Transport(UDP_SCHEME, "Modbus over UDP", _UDP, _AIO_UDP, pipelines=True, mbap=True),
}


def transport_of(port: object) -> Transport:
    """The row of ``port`` (ValueError for a URL no one opens, as `scheme_of`)."""
    return TRANSPORTS[scheme_of(port)]


class LinkRevival:
    """When a master's link comes back after its port or connection failed (a USB
    adapter pulled out, a server restarted): at the next request, then on the
    back-off of `pyrtu.drivers.reconnect` while it stays away; a request between two
    attempts fails at once with a `PortError` naming ``where`` and saying when the
    next attempt is due (``down``: what the link is meanwhile, "not open" for a
    serial port).  The first failed attempt of an outage is logged once (warning),
    the attempt that ends it too (info); ``verb``: "reopen" (a serial port) or
    "reconnect".  Nothing is attempted once the master is closed (``closed``)."""

    def __init__(
        self,
        where: str,
        backoff: Backoff | None = None,
        *,
        verb: str = "reconnect",
        down: str = "not connected",
    ) -> None:
        self.where = where
        self.reconnect = Reconnect(backoff)
        self.closed = False
        self._verb = verb
        self._down = down

    def _before(self) -> float:
        if self.closed:
            raise PortError(self.where, "the master is closed")
        now = time.monotonic()
        r = self.reconnect
        if not r.due(now):
            assert r.outage is not None
            raise PortError(
                self.where,
                f"{self._down} ({r.outage.error}); the next attempt in {r.wait(now):.2f} s",
            )
        return now

    def _failed(self, now: float, exc: PortError) -> None:
        if self.reconnect.failed(now, exc):
            log.warning("%s; %sing on the back-off", exc, self._verb)

    def _worked(self) -> None:
        outage = self.reconnect.recovered(time.monotonic())
        if outage is not None:
            log.info("%s: %sed after %d failed attempts", self.where, self._verb, outage.attempts)

    def attempt(self, revive: Callable[[], None]) -> None:
        """``revive`` now if it is due; `PortError` when it fails or is not due."""
        now = self._before()
        try:
            revive()
        except PortError as exc:
            self._failed(now, exc)
            raise
        self._worked()

    async def attempt_async(self, revive: Callable[[], Awaitable[None]]) -> None:
        """`attempt` for an asyncio link's ``revive``."""
        now = self._before()
        try:
            await revive()
        except PortError as exc:
            self._failed(now, exc)
            raise
        self._worked()


class Link(Protocol):
    """What a master calls on its transport (besides ``transact``, sync or async).

    A link also has what `pyrtu.drivers.master.MasterBase` forwards to it by name
    (``line``, ``port``, ``url``, ``mode``, ``t35``, ``echo``, ``broadcast_delay``,
    ``last_answer_time``; a TCP link raises AttributeError for ``line`` and
    ``port``): those are declared once, typed and documented, on MasterBase."""

    timeout: float
    retries: int

    @property
    def counters(self) -> dict[str, int]: ...

    def address(self, slave: Any, broadcasting: bool) -> tuple[Any, int | None]: ...
    def count_bad(self) -> None: ...
    def set_rules(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None: ...
    def describe(self) -> str: ...


__all__ = [
    "MBAPS_SCHEME",
    "MBAP_SCHEMES",
    "RTU_TCP_SCHEME",
    "TCP_SCHEME",
    "TRANSPORTS",
    "UDP_SCHEME",
    "Call",
    "Link",
    "LinkRevival",
    "Transport",
    "check_in_flight",
    "check_retries",
    "check_seconds",
    "check_tls",
    "scheme_of",
    "transport_of",
]
