"""Modbus over UDP: the links of `pyrtu.Master` and `pyrtu.drivers.aio.AsyncMaster` on
``udp://host[:502]`` (one row of `pyrtu.drivers.links.TRANSPORTS`).

The framing is Modbus TCP's (Messaging on TCP/IP Implementation Guide V1.0b,
3.1.3), one ADU per datagram, as pymodbus's ``ModbusUdpClient``, Home Assistant's
``type: udp`` and Node-RED's UDP client send it: the 7-byte MBAP header (transaction
id, protocol id 0, length, unit id) and the PDU; the server answers with the
request's transaction id and unit id in one datagram.  ``Master("udp://plc")`` is the
same class as on a serial line or ``tcp://``, with the same methods, checks and
decoders, and what a TCP master answers for its line properties (`pyrtu.tcp.link`):
``mode`` is ``"udp"``, no ``line`` nor ``port``, unit ids 0..255 as on ``tcp://``.

What UDP changes:

* **No connection.**  Nothing is sent when the master is made: the socket is only
  *connected* to the server's address (which resolves the host name: an unknown
  host is a `PortError` at once), so the kernel drops datagrams from any other
  address and port before they reach the master.
* **Datagrams get lost.**  A request unanswered within ``timeout`` is
  `NoResponseError`, and with ``retries`` it is sent again, under a new transaction
  id each time: the recovery UDP expects.
* **Stale answers are dropped, not taken.**  An answer whose transaction id is not
  that of a request in flight (the late answer to an attempt that timed out, a
  duplicate) is dropped and counted (``late``); the master goes on waiting for its
  own.  A datagram that is not exactly one whole valid ADU (a protocol id other
  than 0, a length field that does not end the datagram) is dropped and counted
  (``frame_errors``); nothing else happens: there is no stream to lose.
* **A closed port says so.**  When the host answers a request with ICMP "port
  unreachable" (nothing listens there), the request fails at once with
  `NoResponseError` saying so, rather than after the whole timeout; a retry sends
  it again.
* ``AsyncMaster`` keeps up to ``max_in_flight`` requests on the wire at once (their
  answers matched by transaction id), as on ``tcp://``.

Each datagram is framed by the backend's MBAP parser (C: csrc's rtu_mbap_parse, or
the twin), with the sans-I/O `pyrtu.tcp.protocol.TcpClientProtocol` matching the
answers: the counters, log lines (``pyrtu -vv``) and errors of ``tcp://``.
"""

from __future__ import annotations

import asyncio
import logging
import selectors
import socket
import time
from collections.abc import Callable, Sequence
from typing import Any, cast

from pyrtu.core import _backend
from pyrtu.core.line import LineConfig
from pyrtu.core.mbap import MbapFrame
from pyrtu.core.timing import positive_seconds
from pyrtu.drivers._portname import UDP_SCHEME
from pyrtu.drivers.links import check_in_flight
from pyrtu.pdu.errors import ModbusError, NoResponseError, PortError
from pyrtu.pdu.requests import Call
from pyrtu.protocol.client_actions import answer_pdu
from pyrtu.tcp.client import (
    Awaiting,
    RequestWindow,
    TcpClientState,
    connect_error,
    parse_tcp_url,
    where_of,
)
from pyrtu.tcp.link import _TcpBase
from pyrtu.tcp.protocol import TcpClientProtocol

log = logging.getLogger("pyrtu.drivers.master")

#: what one read may take: any datagram whole (one longer than an ADU is dropped
#: as such, never cut down to something that looks like one)
MAX_DATAGRAM = 65535
#: the `NoResponseError` text of a request the host refused (ICMP port unreachable)
UNREACHABLE = "{where}: port unreachable (nothing listens there)"

Parse = Callable[[bytes, str], Sequence[MbapFrame]]


def parse_udp_url(url: str) -> tuple[str, int]:
    """(host, port) of ``udp://host[:port]`` (port 502 by default; IPv6 as
    ``[::1]``); ValueError naming the URL."""
    return parse_tcp_url(url, (UDP_SCHEME,))


def _result(call: Call, answer: bytes | None, end: float | None) -> tuple[Any, float]:
    value = None if call.decode is None or answer is None else call.decode(answer)
    return value, time.monotonic() if end is None or answer is None else end


def _answer_of(result: bytes | ModbusError | None) -> bytes | None:
    if isinstance(result, ModbusError):
        raise result
    return result


class _UdpBase(TcpClientState, _TcpBase):
    """What both UDP links share: the URL, the protocol, the counters."""

    what = "Modbus over UDP"
    mode = "udp"

    def __init__(self, url: str, timeout: float, retries: int, max_in_flight: int) -> None:
        self.url = url
        self.host, self.udp_port = parse_udp_url(url)
        self.where = where_of(self.host, self.udp_port, UDP_SCHEME)
        self.retries = retries
        self._proto = TcpClientProtocol(
            timeout=positive_seconds(timeout, "timeout"),
            max_in_flight=max_in_flight,
            where=self.where,
        )

    @staticmethod
    def check_port(port: str) -> None:
        """ValueError naming ``port`` unless it is ``udp://HOST[:PORT]``."""
        parse_udp_url(port)

    def _counters(self) -> dict[str, int]:
        return self._proto.counters

    def _refused(self) -> None:
        self._proto.refused(UNREACHABLE.format(where=self.where))


class UdpLink(_UdpBase):
    """`pyrtu.Master`'s link on ``udp://`` (blocking, one request at a time)."""

    @classmethod
    def open(
        cls, port: str, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> UdpLink:
        """The link of `pyrtu.drivers.links.TRANSPORTS` (``udp://``)."""
        return cls(port, options["timeout"], options["retries"], options.get("backend"))

    def __init__(self, url: str, timeout: float, retries: int, backend: str | None = None) -> None:
        super().__init__(url, timeout, retries, 1)
        self._parse: Parse = _backend.backend(backend).parse_tcp_stream
        self._closed = False
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                self.host, self.udp_port, type=socket.SOCK_DGRAM
            )[0]
            self._sock = socket.socket(family, kind, proto)
        except OSError as exc:
            raise connect_error(self.where, exc, timeout) from exc
        try:
            self._sock.connect(address)  # (no packet: the kernel's filter and route)
        except OSError as exc:
            self._sock.close()
            raise connect_error(self.where, exc, timeout) from exc
        self._sock.setblocking(False)
        self._readable = selectors.DefaultSelector()  # (any descriptor number, not select()'s)
        self._readable.register(self._sock, selectors.EVENT_READ)

    def transact(self, call: Call) -> tuple[Any, float]:
        answered, raw = call.decode is not None, call.decode is answer_pdu
        for attempt in range(self.retries + 1):
            try:
                answer = self._once(call.slave, call.pdu, answered, raw)
                break
            except NoResponseError:
                if attempt == self.retries:
                    raise
        return _result(call, answer, self._proto.answer_end)

    def _once(self, unit: int, pdu: bytes, answered: bool, raw: bool) -> bytes | None:
        """One attempt: the request's datagram out, datagrams read until its answer,
        an error, or its deadline."""
        proto = self._proto
        if self._closed:
            raise PortError(self.where, "the master is closed")
        tid, data = proto.send_request(unit, pdu, time.monotonic(), answered=answered, raw=raw)
        self._send(tid, data)
        wait = self._readable.select
        while True:
            while (done := proto.next_result()) is not None:
                if done[0] == tid:
                    return _answer_of(done[1])
            deadline = proto.deadline()
            assert deadline is not None  # (its request is in flight: no result yet)
            readable = wait(max(0.0, deadline - time.monotonic()))
            now = time.monotonic()
            if readable:
                self._read(tid, now)
            proto.handle_timer(now)  # (also when datagrams keep coming: none is ours)

    def _send(self, tid: int, data: bytes) -> None:
        for attempt in range(2):
            try:
                self._sock.send(data)
                return
            except ConnectionRefusedError:
                # the ICMP error of an earlier datagram, reported at this send (which
                # sent nothing): send again; refused twice, nothing listens there
                if attempt:
                    self._refused()
            except OSError as exc:
                self._proto.cancel(tid)
                raise PortError(self.where, f"send failed: {exc}") from exc

    def _read(self, tid: int, now: float) -> None:
        """Every datagram waiting, each an answer or dropped (see the module doc)."""
        while True:
            try:
                data = self._sock.recv(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                self._refused()
                return
            except OSError as exc:
                self._proto.cancel(tid)
                raise PortError(self.where, f"receive failed: {exc}") from exc
            self._proto.receive_datagram(data, now, self._parse)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._readable.close()
            self._sock.close()


class _Endpoint(Awaiting, asyncio.DatagramProtocol):
    """The event loop's side of an `AsyncUdpLink`: each datagram an answer (or
    dropped), the futures of the requests in flight resolved from the protocol."""

    def __init__(self, proto: TcpClientProtocol, parse: Parse, refused: Callable[[], None]):
        super().__init__(proto)
        self.parse = parse
        self.refused = refused
        self.transport: asyncio.DatagramTransport | None = None
        #: set while a datagram is handed to the transport: an ICMP error reported
        #: then is an earlier datagram's (`send`)
        self.sending = False
        self.send_refused = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)  # (3.11's is no subclass)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.proto.receive_datagram(data, time.monotonic(), self.parse)
        self.dispatch()

    def error_received(self, exc: Exception) -> None:
        if self.sending and isinstance(exc, ConnectionRefusedError):
            self.send_refused = True
            return
        if isinstance(exc, ConnectionRefusedError):
            self.refused()
        else:  # what a send or a receive raised (a network unreachable...)
            log.debug("%s: %s", self.proto.where, exc)
            self.proto.refused(f"{self.proto.where}: {exc}")
        self.dispatch()

    def connection_lost(self, exc: Exception | None) -> None:
        self.proto.connection_lost(str(exc) if exc else "the master is closed")
        self.dispatch()
        self.stop_timer()

    def send(self, data: bytes) -> None:
        """``data`` out in one datagram (sent again once if the kernel reported an
        earlier datagram's ICMP error instead of sending it)."""
        transport = self.transport
        assert transport is not None
        for _ in range(2):
            self.sending, self.send_refused = True, False
            try:
                transport.sendto(data)
            finally:
                self.sending = False
            if not self.send_refused:
                return
        self.refused()


class AsyncUdpLink(_UdpBase):
    """`pyrtu.drivers.aio.AsyncMaster`'s link on ``udp://``: the socket opened at the
    first request (or `connect`), up to ``max_in_flight`` requests on the wire."""

    @classmethod
    def open(
        cls, port: str, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> AsyncUdpLink:
        """The link of `pyrtu.drivers.links.TRANSPORTS` (``udp://``)."""
        return cls(
            port, options["timeout"], options["retries"], max_in_flight, options.get("backend")
        )

    def __init__(
        self,
        url: str,
        timeout: float,
        retries: int,
        max_in_flight: int = 1,
        backend: str | None = None,
    ) -> None:
        super().__init__(url, timeout, retries, check_in_flight(max_in_flight, True))
        self._parse: Parse = _backend.backend(backend).parse_tcp_stream
        self._window = RequestWindow(max_in_flight)
        self._endpoint: _Endpoint | None = None
        self._opening: asyncio.Lock | None = None

    async def _opened(self) -> _Endpoint:
        if self._endpoint is None:
            if self._opening is None:
                self._opening = asyncio.Lock()
            async with self._opening:
                if self._endpoint is None:
                    loop = asyncio.get_running_loop()
                    try:
                        _, endpoint = await loop.create_datagram_endpoint(
                            lambda: _Endpoint(self._proto, self._parse, self._refused),
                            remote_addr=(self.host, self.udp_port),
                        )
                    except OSError as exc:
                        raise connect_error(self.where, exc, self._proto.timeout) from exc
                    self._endpoint = endpoint
        return self._endpoint

    async def connect(self) -> None:
        """Open the socket now (not at the first request); a `PortError` when the
        host name does not resolve."""
        await self._opened()

    async def transact(self, call: Call) -> tuple[Any, float]:
        endpoint = self._endpoint or await self._opened()
        answered, raw = call.decode is not None, call.decode is answer_pdu
        for attempt in range(self.retries + 1):
            try:
                answer = await self._request(endpoint, call.slave, call.pdu, answered, raw)
                break
            except NoResponseError:
                if attempt == self.retries:
                    raise
        # (pipelined: this answer's time is the latest read when the await resumed)
        return _result(call, answer, self._proto.answer_end)

    async def value(self, call: Call) -> Any:
        """`transact`'s value (the request methods' path, as on ``tcp://``)."""
        return (await self.transact(call))[0]

    async def _request(
        self, endpoint: _Endpoint, unit: int, pdu: bytes, answered: bool, raw: bool
    ) -> bytes | None:
        proto, window = self._proto, self._window
        loop = asyncio.get_running_loop()
        if window.free and not window.queue:  # (a turn at once: no await)
            window.free -= 1
        else:
            await window.wait_turn(loop)
        try:
            transport = endpoint.transport
            if transport is None or transport.is_closing():
                raise PortError(self.where, "the master is closed")
            tid, data = proto.send_request(unit, pdu, time.monotonic(), answered=answered, raw=raw)
            fut: asyncio.Future[bytes | None] = loop.create_future()
            endpoint.waiters[tid] = fut
            endpoint.send(data)
            endpoint.dispatch()  # (a broadcast's None; else the timer armed)
            try:
                return await fut
            except asyncio.CancelledError:
                endpoint.waiters.pop(tid, None)
                proto.cancel(tid)
                raise
        finally:
            window.release()

    async def close(self) -> None:
        endpoint = self._endpoint
        if endpoint is not None and endpoint.transport is not None:
            endpoint.transport.close()
        await asyncio.sleep(0)


__all__ = ["MAX_DATAGRAM", "AsyncUdpLink", "UdpLink", "parse_udp_url"]
