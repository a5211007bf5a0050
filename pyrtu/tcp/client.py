"""Modbus TCP clients: a blocking one and an asyncio one over `TcpClientProtocol`.

``tcp://host:port`` (Messaging on TCP/IP Implementation Guide V1.0b; port 502 by
default).  Both send a PDU to a unit and return the response PDU, raising the
typed errors of `pyrtu.pdu.errors`::

    with TcpClient("tcp://127.0.0.1:5020", timeout=1.0) as c:
        pdu = c.request(1, pyrtu.pdu.read_request(3, 0, 10))

    async with await AsyncTcpClient.connect("tcp://127.0.0.1:5020") as c:
        answers = await asyncio.gather(*(c.request(1, p) for p in pdus))  # pipelined

The asyncio client keeps up to ``max_in_flight`` requests on the wire at once (the
server answers them by transaction id, in any order); the blocking one sends one
at a time, each transaction (send, wait, read the answer whole, drop late ones) one
call of a `pyrtu.drivers.xfer.TcpXferRunner`: C (csrc/rtu_tcp_io.c, the GIL
released) or, with ``backend="python"``, its twin.  ``rtu+tcp://host:port`` (RTU
frames over a TCP socket, as serial device servers carry them) is a serial line
without wire timing: `rtu_over_tcp` opens it as a pyserial object for the serial
master.
"""

from __future__ import annotations

import asyncio
import errno
import os
import select
import socket
import ssl
import struct
import time
from collections import deque
from typing import Any
from urllib.parse import urlsplit

import serial
from serial.urlhandler.protocol_socket import POLL_TIMEOUT
from serial.urlhandler.protocol_socket import Serial as _PySerialSocket

from pyrtu.core import _backend
from pyrtu.core import _tls as _ctls
from pyrtu.core._closing import AsyncClosing, Closing
from pyrtu.core._forward import Forward, Settable
from pyrtu.core._tls import CTlsConnection, CTlsError
from pyrtu.core._types import BytesLike
from pyrtu.core.mbap import MAX_LENGTH, MIN_LENGTH
from pyrtu.drivers import xfer, xfer_runners
from pyrtu.drivers._portname import MBAP_SCHEMES, MBAPS_SCHEME, RTU_TCP_SCHEME
from pyrtu.drivers._ptimer import rearm
from pyrtu.pdu.errors import ModbusError, PortError
from pyrtu.tcp.protocol import TcpClientProtocol, check_timeout
from pyrtu.tcp.sockets import set_nodelay
from pyrtu.tcp.tls import MBAPS_PORT, remember, session_of, wrap

DEFAULT_PORT = 502
_monotonic = time.monotonic
_HEAD = struct.Struct(">HHH")  # an MBAP header's transaction id, protocol id, length


def parse_tcp_url(url: str, schemes: tuple[str, ...] = ("tcp",)) -> tuple[str, int]:
    """(host, port) of ``tcp://host[:port]`` (IPv6 as ``[::1]``); ValueError naming the URL."""
    if not isinstance(url, str):
        raise TypeError(f"url must be a string, not {type(url).__name__}")
    parts = urlsplit(url)
    if parts.scheme not in schemes:
        raise ValueError(f"{url!r}: the scheme must be {' or '.join(s + '://' for s in schemes)}")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"{url!r}: the port must be 0..65535") from None
    if not parts.hostname or parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError(f"{url!r}: expected {parts.scheme}://HOST[:PORT]")
    default = MBAPS_PORT if parts.scheme == MBAPS_SCHEME else DEFAULT_PORT
    return parts.hostname, default if port is None else port


def where_of(host: str, port: int, scheme: str = "tcp") -> str:
    return f"{scheme}://[{host}]:{port}" if ":" in host else f"{scheme}://{host}:{port}"


def _tls_of(url: str, tls: ssl.SSLContext | None) -> ssl.SSLContext | None:
    """The TLS context of ``url``: required for ``mbaps://``, refused for ``tcp://``."""
    mbaps = urlsplit(url).scheme == MBAPS_SCHEME
    if mbaps and not isinstance(tls, ssl.SSLContext):
        raise ValueError(
            f"{url}: tls: an mbaps:// URL needs the client's TLS context "
            "(pyrtu.security.tls.client_context(cert, key, ca))"
        )
    if not mbaps and tls is not None:
        raise ValueError(f"{url}: tls: only an mbaps:// URL takes a TLS context")
    return tls


def _raise(result: bytes | ModbusError | None) -> bytes | None:
    if isinstance(result, ModbusError):
        raise result
    return result


def connect_error(where: str, exc: BaseException, timeout: float) -> PortError:
    """The `PortError` of a connection not made (every TCP connect of pyrtu's says it
    this way): what the OS said (``Connection refused``, also where asyncio words it
    "Connect call failed"), or how long was waited for a timeout (whose text is
    empty, or a bare "timed out")."""
    reason = exc
    if isinstance(exc, serial.SerialException) and isinstance(exc.__context__, OSError):
        reason = exc.__context__  # pyserial's socket:// puts the socket's error in its text
    if isinstance(reason, CTlsError):  # (the C path's, in the ssl module's words)
        text = (
            f"TLS: the server's certificate: {reason.message}"
            if reason.kind == "verify"
            else f"TLS handshake failed: {reason.message}"
        )
    elif isinstance(reason, ssl.SSLCertVerificationError):
        text = f"TLS: the server's certificate: {reason.verify_message or reason.reason}"
    elif isinstance(reason, ssl.SSLError):  # (its errno is OpenSSL's, not the OS's)
        text = f"TLS handshake failed: {reason.reason or reason}"
    elif isinstance(reason, TimeoutError | asyncio.TimeoutError):
        text = f"timed out after {timeout:g} s"
    elif isinstance(reason, socket.gaierror) and reason.strerror:
        text = reason.strerror  # (a resolver's code, not an errno)
    elif isinstance(reason, OSError) and reason.errno:
        text = os.strerror(reason.errno)
    else:
        text = str(reason) or type(reason).__name__
    return PortError(where, f"cannot connect: {text}")


#: how long pyserial's socket:// (under ``rtu+tcp://``) waits for the connection
_SOCKET_CONNECT_TIMEOUT: float = POLL_TIMEOUT


def parse_rtu_tcp_url(url: str) -> tuple[str, int]:
    """(host, port) of ``rtu+tcp://host[:port]``; ValueError naming the URL."""
    return parse_tcp_url(url, (RTU_TCP_SCHEME,))


class _SocketLine(_PySerialSocket):  # type: ignore[misc]  # (pyserial is untyped)
    """pyserial's ``socket://`` whose close does not sleep: pyserial's sleeps 0.3 s
    after it ("in case of quick reconnects"), on the caller's thread, an asyncio
    master's event loop when a device server goes away; a master reconnects on its
    own back-off (`pyrtu.drivers.links.LinkRevival`)."""

    _socket: socket.socket | None
    is_open: bool

    def close(self) -> None:
        sock = self._socket
        if self.is_open and sock is not None:
            self._socket = None
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:  # (the peer reset it, or it never connected)
                pass
            sock.close()
        self.is_open = False


def rtu_over_tcp(url: str) -> Any:
    """A pyserial object over TCP for ``rtu+tcp://host[:port]``: RTU frames (CRC kept)
    to a serial device server; no wire timing, so use it with ``t35=0``."""
    host, port = parse_rtu_tcp_url(url)
    netloc = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    try:
        link = _SocketLine(f"socket://{netloc}", timeout=0)
    except (serial.SerialException, OSError) as exc:
        raise connect_error(url, exc, _SOCKET_CONNECT_TIMEOUT) from exc
    set_nodelay(getattr(link, "_socket", None))  # pyserial's socket:// does not
    return link


class TcpClientState:
    """What a TCP client reads from (and sets on) its protocol."""

    _proto: TcpClientProtocol
    timeout = Settable[float]("_proto", check_timeout)
    last_answer_time = Forward[float | None](
        "_proto",
        "answer_end",
        "When the latest answer was read (monotonic seconds), or None before the first.",
    )

    @property
    def counters(self) -> dict[str, int]:
        return dict(self._proto.counters)


class TcpClient(TcpClientState, Closing):
    """A blocking Modbus TCP client: one request at a time on one connection.  Each
    transaction's I/O is one call of the backend's `pyrtu.drivers.xfer.TcpXferRunner`
    (C: csrc/rtu_tcp_io.c, the GIL released; ``backend="python"``: the twin)."""

    def __init__(
        self,
        url: str,
        *,
        timeout: float = 1.0,
        connect_timeout: float | None = None,
        backend: str | None = None,
        tls: ssl.SSLContext | None = None,
    ) -> None:
        self.host, self.port = parse_tcp_url(url, MBAP_SCHEMES)
        self._tls = _tls_of(url, tls)
        self.where = where_of(self.host, self.port, "tcp" if self._tls is None else MBAPS_SCHEME)
        self._backend = _backend.backend(backend)
        self._closed = True  # (until `_open` connects)
        self._proto = TcpClientProtocol(timeout=timeout, max_in_flight=1, where=self.where)
        self._connect_timeout = check_timeout(
            timeout if connect_timeout is None else connect_timeout, "connect_timeout"
        )
        self._open()

    def _open(self) -> None:
        """Connect (TCP, then the TLS handshake of ``mbaps://``, resuming the session
        of the last connection to the server); `PortError` when it cannot."""
        ct, be = self._connect_timeout, self._backend
        try:
            sock = socket.create_connection((self.host, self.port), timeout=ct)
        except OSError as exc:
            raise connect_error(self.where, exc, ct) from exc
        set_nodelay(sock)
        self._sock = sock
        self._ctls: CTlsConnection | None = None
        accelerated = None if self._tls is None else _ctls.accelerator(self._tls, be)
        if accelerated is not None:  # mbaps:// in C: the handshake, then tcp://'s runner
            sock.setblocking(False)
            try:
                self._ctls = accelerated.connect(sock.fileno(), self.host, self.port, ct)
            except OSError as exc:
                sock.close()
                raise connect_error(self.where, exc, ct) from exc
            self._accelerated = accelerated
            self._runner = xfer_runners.tcp_xfer_runner(be, sock, self._ctls.io, self._ctls.message)
        elif self._tls is not None:  # mbaps:// in Python: the handshake within the connect timeout
            try:
                self._sock = wrap(sock, self._tls, self.host, self.port)
            except OSError as exc:
                sock.close()
                raise connect_error(self.where, exc, ct) from exc
            # blocking, with the timeout as bound: select() sees the records, and a
            # recv() waits for the rest of a record it has begun; the transaction in
            # Python (`_tls_transact`): the xfer runners read the socket's descriptor,
            # under TLS the records, not the PDUs
            self._sock.settimeout(self._proto.timeout)
        else:
            sock.setblocking(False)
            self._runner = xfer_runners.tcp_xfer_runner(be, sock)
        self._closed = False

    @property
    def broken(self) -> bool:
        """Whether the connection is unusable (the server closed it, a send or receive
        failed, a bad header came, or `close` ran): `reconnect` makes a new one."""
        return self._closed or self._proto.broken is not None

    def reconnect(self) -> None:
        """A new connection to the same server in place of this one (after the server
        closed it, or it failed): the same counters and transaction ids, the TLS
        session resumed on ``mbaps://``.  `PortError` when it cannot connect; the
        client is left unconnected (`broken`), the error its reason."""
        self.close()
        self._proto.reset()
        try:
            self._open()
        except PortError as exc:
            self._proto.connection_lost(str(exc).removeprefix(f"{self.where}: "))
            raise

    def request(
        self, unit: int, pdu: BytesLike, *, answered: bool | None = None, raw: bool = False
    ) -> bytes | None:
        """The response PDU of ``pdu`` sent to ``unit`` (None for unit 0, a broadcast,
        unless ``answered=True``: unit 0 to a TCP device itself, 4.4.1.2).  An
        exception response raises `ExceptionResponseError`, or with ``raw=True`` is
        returned as its PDU (function code | 0x80, exception code)."""
        return self.transact(unit, pdu, answered, raw)[0]

    def transact(
        self, unit: int, pdu: BytesLike, answered: bool | None, raw: bool
    ) -> tuple[bytes | None, float]:
        """`request`'s answer and when it came (monotonic seconds; now for a
        broadcast): `pyrtu.tcp.link.TcpLink`'s transaction."""
        if self._tls is not None and self._ctls is None:
            return self._tls_transact(unit, pdu, answered, raw)
        proto, runner = self._proto, self._runner
        tid, body, awaited = proto.begin(unit, pdu, answered)
        if self._closed:  # (its descriptor's number may be another file's by now)
            proto.connection_lost(f"send failed: {OSError(errno.EBADF, os.strerror(errno.EBADF))}")
            assert proto.broken is not None
            raise proto.broken
        word = runner.call(tid, unit, body, awaited, proto.timeout)
        while word & xfer.TCP_STATUS == xfer.TCP_INTERRUPTED:  # a signal's handler ran
            word = runner.resume()
        if word & 0xFF == xfer.TCP_ANSWER:  # a response, nothing late; or a broadcast
            if awaited:
                answer = runner.answer[: word >> 8]
                return answer, proto.answered(tid, unit, answer, runner)
            return None, time.monotonic()
        answer = proto.settle(tid, unit, body[0], raw, runner)
        end = proto.answer_end
        return answer, time.monotonic() if answer is None or end is None else end

    def _tls_transact(
        self, unit: int, pdu: BytesLike, answered: bool | None, raw: bool
    ) -> tuple[bytes | None, float]:
        """`transact` over ``mbaps://``: the protocol's events, fed from the TLS socket."""
        proto = self._proto
        now = time.monotonic()
        tid, data = proto.send_request(unit, pdu, now, answered=answered, raw=raw)
        try:
            if self._closed:
                raise OSError(errno.EBADF, os.strerror(errno.EBADF))
            self._sock.sendall(data)
        except OSError as exc:
            proto.connection_lost(f"send failed: {exc}")
        while True:
            done = proto.next_result()
            if done is not None:
                if done[0] == tid:
                    answer = _raise(done[1])
                    end = proto.answer_end
                    return answer, time.monotonic() if answer is None or end is None else end
                continue
            deadline = proto.deadline()
            wait = 0.0 if deadline is None else max(0.0, deadline - time.monotonic())
            readable, _, _ = select.select([self._sock], [], [], wait)
            now = time.monotonic()
            if readable:
                try:
                    chunk = self._sock.recv(65536)
                except OSError as exc:
                    proto.connection_lost(f"receive failed: {exc}")
                    continue
                if not chunk:
                    proto.connection_lost("the server closed the connection")
                    continue
                proto.receive_data(chunk, now)
            else:
                proto.handle_timer(now)

    @property
    def session_reused(self) -> bool:
        """Whether this ``mbaps://`` connection resumed a TLS session (False on tcp://)."""
        if self._ctls is not None:
            return self._ctls.reused
        return isinstance(self._sock, ssl.SSLSocket) and bool(self._sock.session_reused)

    @property
    def tls_path(self) -> str | None:
        """Who runs this ``mbaps://`` connection's TLS: ``"c"`` (the C core over OpenSSL,
        csrc/rtu_tls_io.c) or ``"python"`` (the ssl module); None on tcp://."""
        if self._tls is None:
            return None
        return "c" if self._ctls is not None else "python"

    def close(self) -> None:
        if self._closed:
            return
        if self._ctls is not None:  # (TLS 1.3: the tickets came after the handshake)
            self._accelerated.keep(self.host, self.port, self._ctls)
            self._ctls.close()
        elif self._tls is not None and isinstance(self._sock, ssl.SSLSocket):
            remember(self._sock, self._tls, self.host, self.port)
        self._closed = True
        self._sock.close()

    def __repr__(self) -> str:
        return f"TcpClient({self.where!r})"


class Awaiting:
    """The futures of an asyncio client's requests in flight (TCP: `AsyncTcpClient`;
    UDP: `pyrtu.tcp.udp.AsyncUdpLink`): each resolved from the protocol's results,
    one timer for the first deadline."""

    def __init__(self, proto: TcpClientProtocol) -> None:
        self.proto = proto
        self.waiters: dict[int, asyncio.Future[bytes | None]] = {}
        self.timer: asyncio.TimerHandle | None = None
        self.timer_at = 0.0  # when the timer fires (monotonic seconds)

    def on_timer(self) -> None:
        self.timer = None
        self.proto.handle_timer(time.monotonic())
        self.dispatch()

    def dispatch(self) -> None:
        while (done := self.proto.next_result()) is not None:
            tid, result = done
            fut = self.waiters.pop(tid, None)
            if fut is None or fut.done():
                continue
            if isinstance(result, ModbusError):
                fut.set_exception(result)
            else:
                fut.set_result(result)
        self.arm()

    def arm(self) -> None:
        """A timer for the first deadline of the requests in flight, unless one
        fires before it (an answered request's: it finds nothing expired and
        arms the next; so a transaction answered in time touches no timer)."""
        when = self.proto.deadline()
        if when is not None and (self.timer is None or when < self.timer_at):
            self.timer = rearm(self.timer, when, self.on_timer)
            self.timer_at = when

    def stop_timer(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


class _ClientConnection(Awaiting, asyncio.BufferedProtocol):
    """The event loop's side of an `AsyncTcpClient`: the socket is read straight
    into the scanner's buffer (no bytes object per read: asyncio's plain
    `asyncio.Protocol` allocates 256 KiB for each); the answer of the one request in
    flight, alone in a read, is told by its header and resolves its future here; any
    other read is scanned (C: rtu_tcp_scan; the twin) for its whole ADUs: several in
    flight (pipelined), late answers and bad headers go through the protocol's
    results."""

    def __init__(self, proto: TcpClientProtocol, where: str, scanner: xfer.TcpScanner) -> None:
        super().__init__(proto)
        self.where = where
        self.transport: asyncio.Transport | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.scan = scanner.scan
        self.buf = scanner.buf
        self.view = memoryview(scanner.buf)
        self.n = 0  # bytes in buf: the start of an ADU not read whole yet

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.loop = asyncio.get_running_loop()

    def get_buffer(self, sizehint: int) -> memoryview:
        n = self.n
        return self.view[n:] if n else self.view

    def buffer_updated(self, nbytes: int) -> None:
        now = _monotonic()
        proto = self.proto
        n = self.n + nbytes
        if proto.broken is not None:  # (the stream is lost: nothing more is read)
            self.n = 0
            return
        tid = proto.sole_tid()
        used = 0
        if tid >= 0 and n >= 6:
            # the common read: the answer of the one request in flight, one whole
            # ADU and nothing after it, told by its header alone (as the scan below
            # finds it: used == ans_len == n, no error)
            got, protocol, length = _HEAD.unpack_from(self.buf)
            if got == tid and not protocol and MIN_LENGTH <= length <= MAX_LENGTH:
                used = n if n == 6 + length else 0
        if not used:  # anything else: the backend's scan (C: rtu_tcp_scan)
            scan = self.scan(n, tid if tid >= 0 else 0)
            used = scan.used
            if tid < 0 or not used or used != scan.ans_len or scan.error:
                if used or scan.error:
                    proto.receive_scanned(bytes(self.view[:used]), used, scan.error, now)
                    self.dispatch()
                self._keep(n, used)
                return
        # the one answer awaited, alone: its future resolved here
        result = proto.take_answer(tid, self.buf[6], bytes(self.view[7:used]), now)
        fut = self.waiters.pop(tid, None)
        if fut is not None and not fut.done():
            if type(result) is bytes:  # (the common end: a response)
                fut.set_result(result)
            elif isinstance(result, ModbusError):
                fut.set_exception(result)
            else:
                fut.set_result(result)
        if used == n:
            self.n = 0
        else:
            self._keep(n, used)

    def _keep(self, n: int, used: int) -> None:
        """After a read (``n`` bytes in the buffer, ``used`` of them resolved): the
        partial ADU after them moves to the buffer's start."""
        if used:
            rest = n - used
            if rest:
                self.buf[:rest] = bytes(self.view[used:n])  # a partial ADU stays
            n = rest
        self.n = 0 if self.proto.broken is not None else n

    def eof_received(self) -> bool | None:
        self.proto.connection_lost("the server closed the connection")
        self.dispatch()
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self.proto.connection_lost(str(exc) if exc else "connection closed")
        self.dispatch()
        self.stop_timer()


class RequestWindow:
    """The turns of an `AsyncTcpClient`'s requests: ``free`` of ``max_in_flight``
    on the wire; the others wait in order (as an `asyncio.Semaphore`, without its
    coroutines on the common path: a caller with a free turn takes it without an
    await)."""

    __slots__ = ("free", "queue")

    def __init__(self, size: int) -> None:
        self.free = size
        self.queue: deque[asyncio.Future[None]] = deque()

    async def wait_turn(self, loop: asyncio.AbstractEventLoop) -> None:
        """Wait until `release` hands this caller a turn."""
        fut: asyncio.Future[None] = loop.create_future()
        self.queue.append(fut)
        try:
            await fut
        except asyncio.CancelledError:
            if fut.cancelled():
                if fut in self.queue:
                    self.queue.remove(fut)
            else:
                self.release()  # handed a turn, then cancelled: the next one's
            raise

    def release(self) -> None:
        """A turn is over: the first caller still waiting gets it, else it is free."""
        queue = self.queue
        while queue:
            fut = queue.popleft()
            if not fut.done():
                fut.set_result(None)
                return
        self.free += 1


class _Dial:
    """How an `AsyncTcpClient` connects, kept for its reconnects: where, the TLS
    context (``mbaps://``: the session of the last connection to the server resumed,
    through `pyrtu.core._tls.resuming`), the connect timeout, the backend."""

    def __init__(
        self,
        host: str,
        port: int,
        context: ssl.SSLContext | None,
        connect_timeout: float,
        backend: Any,
    ) -> None:
        self.host, self.port = host, port
        self.context = context
        self.connect_timeout = connect_timeout
        self.backend = backend

    async def open(self, proto: TcpClientProtocol) -> _ClientConnection:
        """A connection for ``proto``; `PortError` when it cannot be made."""
        host, port, context, ct = self.host, self.port, self.context, self.connect_timeout
        where = proto.where
        scanner = xfer_runners.tcp_scanner(self.backend)
        loop = asyncio.get_running_loop()
        session = None if context is None else session_of(context, host, port)
        try:
            with _ctls.resuming(session):
                _, conn = await asyncio.wait_for(
                    loop.create_connection(
                        lambda: _ClientConnection(proto, where, scanner),
                        host,
                        port,
                        ssl=context,
                        server_hostname=None if context is None else host,
                    ),
                    ct,
                )
        except (OSError, asyncio.TimeoutError) as exc:
            raise connect_error(where, exc, ct) from exc
        transport = conn.transport
        set_nodelay(transport.get_extra_info("socket") if transport else None)
        if transport is not None:
            self.keep_session(transport)
        return conn

    def keep_session(self, transport: asyncio.BaseTransport) -> None:
        """Keep the connection's TLS session for the next connect (TLS 1.2: there
        after the handshake; TLS 1.3: after the tickets, so again at the close)."""
        tls = transport.get_extra_info("ssl_object")
        if self.context is not None and tls is not None:
            remember(tls, self.context, self.host, self.port)


class AsyncTcpClient(TcpClientState, AsyncClosing):
    """An asyncio Modbus TCP client: up to ``max_in_flight`` requests on the wire at
    once.  ``backend``: whose scan reads the answers (`pyrtu.drivers.xfer.TcpScanner`:
    C, rtu_tcp_scan, or ``"python"``: the twin)."""

    def __init__(
        self,
        conn: _ClientConnection,
        host: str,
        port: int,
        max_in_flight: int,
        dial: _Dial,
    ) -> None:
        self._conn = conn
        self._proto = conn.proto
        self.host, self.port = host, port
        self.where = conn.where
        self._window = RequestWindow(max_in_flight)
        assert conn.loop is not None  # (connected: connection_made ran)
        self._loop = conn.loop
        self._dial = dial

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        timeout: float = 1.0,
        connect_timeout: float | None = None,
        max_in_flight: int = 16,
        backend: str | None = None,
        tls: ssl.SSLContext | None = None,
    ) -> AsyncTcpClient:
        host, port = parse_tcp_url(url, MBAP_SCHEMES)
        context = _tls_of(url, tls)
        where = where_of(host, port, "tcp" if context is None else MBAPS_SCHEME)
        proto = TcpClientProtocol(timeout=timeout, max_in_flight=max_in_flight, where=where)
        ct = check_timeout(
            timeout if connect_timeout is None else connect_timeout, "connect_timeout"
        )
        dial = _Dial(host, port, context, ct, _backend.backend(backend))
        return cls(await dial.open(proto), host, port, max_in_flight, dial)

    @property
    def broken(self) -> bool:
        """Whether the connection is unusable (the server closed it, it failed, a bad
        header came, or `close` ran): `reconnect` makes a new one."""
        transport = self._conn.transport
        return self._proto.broken is not None or transport is None or transport.is_closing()

    async def reconnect(self) -> None:
        """A new connection to the same server in place of this one (after the server
        closed it, or it failed): the same counters, the TLS session resumed on
        ``mbaps://``.  `PortError` when it cannot connect; the client is left
        unconnected (`broken`), the error its reason."""
        dial = self._dial
        old, proto = self._conn, self._proto
        proto.connection_lost("reconnecting")  # (what was in flight fails, if anything)
        old.dispatch()
        old.stop_timer()
        # the old connection's late events (its close) go to a protocol of its own
        old.proto = TcpClientProtocol(timeout=proto.timeout, max_in_flight=1, where=self.where)
        await self.close()
        proto.reset()
        try:
            self._conn = await dial.open(proto)
        except PortError as exc:
            proto.connection_lost(str(exc).removeprefix(f"{self.where}: "))
            old.proto = proto  # (broken: the requests say why; late events change nothing)
            raise
        assert self._conn.loop is not None
        self._loop = self._conn.loop

    @property
    def session_reused(self) -> bool:
        """Whether this ``mbaps://`` connection resumed a TLS session (False on tcp://)."""
        transport = self._conn.transport
        tls = None if transport is None else transport.get_extra_info("ssl_object")
        return bool(tls is not None and tls.session_reused)

    async def request(
        self, unit: int, pdu: BytesLike, *, answered: bool | None = None, raw: bool = False
    ) -> bytes | None:
        """The response PDU of ``pdu`` sent to ``unit`` (None for unit 0, a broadcast,
        unless ``answered=True``: unit 0 to a TCP device itself, 4.4.1.2).  An
        exception response raises `ExceptionResponseError`, or with ``raw=True`` is
        returned as its PDU (function code | 0x80, exception code).  Cancelling the
        await forgets the request (a late answer is dropped)."""
        window = self._window
        if window.free and not window.queue:  # (a turn at once: no await)
            window.free -= 1
        else:
            await window.wait_turn(self._loop)
        try:
            tid, fut = self._send(unit, pdu, answered, raw)
            try:
                return await fut
            except asyncio.CancelledError:
                self._forget(tid)
                raise
        finally:
            window.release()

    def _send(
        self, unit: int, pdu: BytesLike, answered: bool | None, raw: bool
    ) -> tuple[int, asyncio.Future[bytes | None]]:
        """A request on the wire (its turn taken): its transaction id and the future
        its result resolves (`request`'s, and `pyrtu.tcp.link.AsyncTcpLink`'s, which
        awaits it without a coroutine of this client's in between)."""
        conn = self._conn
        proto = conn.proto
        now = _monotonic()
        tid, data = proto.send_request(unit, pdu, now, answered=answered, raw=raw)
        fut: asyncio.Future[bytes | None] = self._loop.create_future()
        conn.waiters[tid] = fut
        transport = conn.transport
        if transport is None or transport.is_closing():
            proto.connection_lost("the connection is closed")
            conn.dispatch()
        else:
            transport.write(data)
            if proto.has_results():  # a broadcast's None
                conn.dispatch()
            elif conn.timer is None or now + proto.timeout < conn.timer_at:
                conn.arm()
        return tid, fut

    def _forget(self, tid: int) -> None:
        """The await of request ``tid`` was cancelled: a late answer is dropped."""
        self._conn.waiters.pop(tid, None)
        self._conn.proto.cancel(tid)

    async def close(self) -> None:
        transport = self._conn.transport
        if transport is not None:
            self._dial.keep_session(transport)  # (TLS 1.3: the tickets came after the handshake)
            transport.close()
        await asyncio.sleep(0)

    async def exchange(self, unit: int, pdu: BytesLike) -> bytes | None:
        """`request` with ``raw=True``: an exception response as its PDU (the gateway's
        bus interface, as `pyrtu.drivers.aio.AsyncMaster.exchange`)."""
        return await self.request(unit, pdu, raw=True)

    def __repr__(self) -> str:
        return f"AsyncTcpClient({self.where!r})"


__all__ = ["DEFAULT_PORT", "AsyncTcpClient", "TcpClient", "parse_tcp_url", "rtu_over_tcp"]
