"""The Modbus TCP links of `pyrtu.Master` and `pyrtu.drivers.aio.AsyncMaster` (``tcp://``).

``Master("tcp://host:port")`` is the same class as a serial master with this link
(`pyrtu.drivers.links`) in place of the serial line: the same methods, argument checks
and decoders (`pyrtu.pdu.requests`), with the transport of `pyrtu.tcp`: MBAP frames,
transaction ids, no CRC and no wire timing (the length field ends each answer).
``timeout`` and ``retries`` keep their meaning (a retry after `NoResponseError`
only); the line keywords are checked and otherwise unused, so code can switch
transports by the port string (a misspelled keyword is a TypeError on every
transport).  The asyncio master keeps up to ``max_in_flight`` requests on the
connection at once (``asyncio.gather`` of several awaits), for servers that answer
pipelined requests (libmodbus does; pymodbus 3.16's server does not: keep 1).

What `pyrtu.Master` says of its serial line, a TCP master answers for TCP:
``mode`` is ``"tcp"``, ``t35``, ``broadcast_delay`` are 0.0 (no wire timing: the
master keeps no silence and a broadcast returns at once), ``echo`` is False,
``last_answer_time`` is when the latest answer was read (what the poller stamps
values with), ``url`` is the URL given.  ``line`` and ``port`` (the `LineConfig` and
the pyserial port of a serial master) do not exist: reading them raises
AttributeError (``line``'s message names the URL and says why), so
``hasattr(m, "line")`` is False and ``getattr(m, "line", None)`` is None: code
tells a serial master from a TCP one that way.  (Not None: a `LineConfig | None`
would widen the type every caller of ``Master.line`` relies on.)

Unit ids (Messaging on TCP/IP Implementation Guide 4.4.1.2): every method takes
0..255 where a serial master takes 0..247.  0xFF (libmodbus's default, the guide's
recommendation for a TCP device) and 248..254 address what is behind the
connection; 0 in a method that reads (where a serial master refuses the broadcast)
addresses the TCP device itself and its answer is awaited ("the value 0 is also
accepted to communicate directly to a MODBUS/TCP device"); 0 in a write,
``request`` or ``execute`` stays the broadcast (no answer awaited), as through a
gateway.  ``add_rule`` is accepted and does nothing.
"""

from __future__ import annotations

import asyncio
import ssl
import time
from typing import Any

from pyrtu.core.line import LineConfig
from pyrtu.core.rules import LengthRule
from pyrtu.drivers._portname import MBAP_SCHEMES
from pyrtu.drivers.links import LinkRevival, check_in_flight
from pyrtu.pdu.errors import NoResponseError
from pyrtu.pdu.requests import Call
from pyrtu.protocol.client_actions import answer_pdu
from pyrtu.tcp.client import AsyncTcpClient, TcpClient, parse_tcp_url

NO_LINE = (
    "{url}: a {what} master has no serial line (line and port are a serial "
    "master's; see url, timeout, retries)"
)
NO_PORT = "{url}: a {what} master has no serial port (see url)"


#: the slave the argument checks shared with the serial master (0..247) see in
#: place of a unit id only TCP allows
_STAND_IN = 1


class _TcpBase:
    """What both TCP links (and the UDP ones, `pyrtu.tcp.udp`) answer for a serial
    master's line properties."""

    url: str
    timeout: float
    retries: int
    #: the transport, in the words of `describe` and the AttributeErrors
    what = "Modbus TCP"

    @property
    def line(self) -> LineConfig:
        raise AttributeError(NO_LINE.format(url=self.url, what=self.what))

    @property
    def port(self) -> Any:
        raise AttributeError(NO_PORT.format(url=self.url, what=self.what))

    # no wire timing, no echo: the master keeps no silence, a broadcast returns at once
    mode = "tcp"
    t35 = 0.0
    echo = False
    broadcast_delay = 0.0

    @staticmethod
    def address(slave: Any, broadcasting: bool) -> tuple[Any, int | None]:
        """The unit ids only TCP allows (see the module doc) go in place of a stand-in."""
        if type(slave) is int and (248 <= slave <= 255 or (slave == 0 and not broadcasting)):
            return _STAND_IN, slave
        return slave, None

    @staticmethod
    def check_port(port: str) -> None:
        """ValueError naming ``port`` unless it is ``tcp://`` or ``mbaps://HOST[:PORT]``."""
        parse_tcp_url(port, MBAP_SCHEMES)

    def count_bad(self) -> None:
        self._counters()["frame_errors"] = self._counters().get("frame_errors", 0) + 1

    def _counters(self) -> dict[str, int]:
        raise NotImplementedError

    def set_rules(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        """Length rules are not needed on TCP (the MBAP length ends every answer)."""

    def describe(self) -> str:
        return f"{self.url} {self.what}" + (" in TLS" if self.url.startswith("mbaps") else "")


class TcpLink(_TcpBase):
    """`pyrtu.Master`'s link on a Modbus TCP connection (blocking, one at a time;
    each transaction one call of the ``backend``'s `pyrtu.drivers.xfer.TcpXferRunner`:
    C, csrc/rtu_tcp_io.c, the GIL released, or the twin)."""

    @classmethod
    def open(
        cls, port: str, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> TcpLink:
        """The link of `pyrtu.drivers.links.TRANSPORTS` (``tcp://``, ``mbaps://``)."""
        return cls(
            port,
            options["timeout"],
            options["retries"],
            options.get("backend"),
            tls=options["tls"],
        )

    def __init__(
        self,
        url: str,
        timeout: float,
        retries: int,
        backend: str | None = None,
        tls: ssl.SSLContext | None = None,
    ) -> None:
        self.url = url
        self.retries = retries
        self._client = TcpClient(url, timeout=timeout, backend=backend, tls=tls)
        self._revive = LinkRevival(self._client.where)

    @property
    def timeout(self) -> float:
        return self._client.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._client.timeout = value

    def _counters(self) -> dict[str, int]:
        return self._client._proto.counters

    @property
    def counters(self) -> dict[str, int]:
        return self._client.counters

    @property
    def last_answer_time(self) -> float | None:
        return self._client.last_answer_time

    def transact(self, call: Call) -> tuple[Any, float]:
        slave, pdu, decode = call
        args = (slave, pdu, decode is not None, decode is answer_pdu)
        if self._client.broken:
            self._revive.attempt(self._client.reconnect)
        try:
            answer, end = self._client.transact(*args)
        except NoResponseError:
            if not self.retries:
                raise
            answer, end = self._retry(args)
        return (None if decode is None or answer is None else decode(answer)), end

    def _retry(self, args: tuple[Any, bytes, bool, bool]) -> tuple[bytes | None, float]:
        """The retries after a first `NoResponseError` (the last one's is raised)."""
        for attempt in range(self.retries):
            try:
                return self._client.transact(*args)
            except NoResponseError:
                if attempt == self.retries - 1:
                    raise
        raise AssertionError("unreachable")  # (retries > 0: the loop returns or raises)

    def close(self) -> None:
        self._revive.closed = True
        self._client.close()


class AsyncTcpLink(_TcpBase):
    """`pyrtu.drivers.aio.AsyncMaster`'s link on a Modbus TCP connection; connects on the
    first request, keeps up to ``max_in_flight`` requests on the wire; ``backend``:
    whose scan reads the answers (C, rtu_tcp_scan, or the twin)."""

    @classmethod
    def open(
        cls, port: str, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> AsyncTcpLink:
        """The link of `pyrtu.drivers.links.TRANSPORTS` (``tcp://``, ``mbaps://``)."""
        return cls(
            port,
            options["timeout"],
            options["retries"],
            max_in_flight,
            options["tls"],
            options.get("backend"),
        )

    def __init__(
        self,
        url: str,
        timeout: float,
        retries: int,
        max_in_flight: int,
        tls: ssl.SSLContext | None = None,
        backend: str | None = None,
    ) -> None:
        parse_tcp_url(url, MBAP_SCHEMES)  # ValueError now, not at the first request
        self.url = url
        self._tls = tls
        self.retries = retries
        self._timeout = timeout
        self._max_in_flight = check_in_flight(max_in_flight, True)
        self._client: AsyncTcpClient | None = None
        self._connecting: asyncio.Lock | None = None
        self._backend = backend
        self._revive = LinkRevival(url)

    @property
    def timeout(self) -> float:
        return self._timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._timeout = value
        if self._client is not None:
            self._client.timeout = value

    def _counters(self) -> dict[str, int]:
        return {} if self._client is None else self._client._conn.proto.counters

    @property
    def counters(self) -> dict[str, int]:
        return {} if self._client is None else self._client.counters

    @property
    def last_answer_time(self) -> float | None:
        return None if self._client is None else self._client.last_answer_time

    async def _connected(self) -> AsyncTcpClient:
        """The connection: made at the first request, made again (on `LinkRevival`'s
        back-off) at a request after it broke."""
        client = self._client
        if client is None or client.broken:
            if self._connecting is None:
                self._connecting = asyncio.Lock()
            async with self._connecting:
                if self._client is None:
                    self._client = await AsyncTcpClient.connect(
                        self.url,
                        timeout=self._timeout,
                        max_in_flight=self._max_in_flight,
                        tls=self._tls,
                        backend=self._backend,
                    )
                elif self._client.broken:
                    await self._revive.attempt_async(self._client.reconnect)
            client = self._client
        return client

    async def connect(self) -> None:
        """Connect now (not at the first request); nothing when connected."""
        await self._connected()

    async def transact(self, call: Call) -> tuple[Any, float]:
        value = await self.value(call)
        # (pipelined: this answer's time is the latest read when the await resumed;
        # a broadcast's, now)
        end = None if self._client is None else self._client._proto.answer_end
        return value, time.monotonic() if end is None or call.decode is None else end

    async def value(self, call: Call) -> Any:
        """The decoded answer of ``call`` (`transact`'s value; the request methods'
        path): `AsyncTcpClient.request`, its turn and future awaited here (one
        coroutine less per transaction), retried after `NoResponseError`."""
        client = self._client
        if client is None or client.broken:
            client = await self._connected()
        slave, pdu, decode = call
        answered, raw = decode is not None, decode is answer_pdu
        window = client._window
        retries = self.retries
        while True:
            if window.free and not window.queue:  # (a turn at once: no await)
                window.free -= 1
            else:
                await window.wait_turn(client._loop)
            try:
                tid, fut = client._send(slave, pdu, answered, raw)
                try:
                    answer = await fut
                except asyncio.CancelledError:
                    client._forget(tid)
                    raise
            except NoResponseError:
                if not retries:
                    raise
                retries -= 1
                continue
            finally:
                if window.queue:
                    window.release()
                else:  # (`RequestWindow.release` with no one waiting)
                    window.free += 1
            return None if decode is None or answer is None else decode(answer)

    async def close(self) -> None:
        self._revive.closed = True
        if self._client is not None:
            await self._client.close()


__all__ = ["AsyncTcpLink", "TcpLink"]
