"""The gateway's connections: one asyncio protocol per TCP client (Modbus TCP, or
RTU over TCP), reading requests into the gateway and writing its answers.  At DEBUG
level (``pyrtu -vv``) every frame received and sent is logged, whole (the MBAP
header and PDU, or the RTU frame with its CRC), as a serial slave logs its own."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import struct
import time
from typing import Protocol

from pyrtu.core import _backend
from pyrtu.core.frames import FrameKind
from pyrtu.core.mbap import MAX_LENGTH, MAX_PDU, MBAP_HEADER, MIN_LENGTH
from pyrtu.drivers._ptimer import rearm
from pyrtu.security.policy import Identity
from pyrtu.security.tls import TlsSetupError, peer_identity
from pyrtu.tcp.sockets import set_nodelay

from ._live import Liveness
from ._plan import GatewayLimits

log = logging.getLogger("pyrtu.gateway")


class Owner(Protocol):
    """What a connection asks of the gateway that accepted it (`Gateway`)."""

    limits: GatewayLimits
    counters: dict[str, int]
    _connections: dict[int, _Connection]

    def _opened(self, conn: _Connection) -> None: ...
    def _tls_failed(self, conn: _Connection, reason: str) -> None: ...
    def _closed(self, conn: _Connection) -> None: ...
    def _request(self, conn: _Connection, transaction: int, unit: int, pdu: bytes) -> None: ...


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
    def __init__(self, gateway: Owner) -> None:
        self.gateway = gateway
        self.id = 0
        self.transport: asyncio.Transport | None = None
        self.framer = _backend.active.MbapFramer("slave")
        self.closed = False
        self.grace: asyncio.TimerHandle | None = None  # a closing connection's reset
        self.live = Liveness(time.monotonic())
        self.buffered = 0  # bytes read that no complete request has taken yet
        #: who the client is (its address; on TLS its certificate's role and subject)
        self.identity = Identity("?")

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        peer = transport.get_extra_info("peername")
        if isinstance(peer, tuple) and len(peer) >= 2:
            self.identity = Identity(str(peer[0]), int(peer[1]))
        elif peer:
            self.identity = Identity(str(peer))
        sock = transport.get_extra_info("socket")
        set_nodelay(sock)  # asyncio sets it too; said here, not left to its version
        if sock is not None:
            with contextlib.suppress(OSError):  # bound the kernel's share of unread answers
                sock.setsockopt(
                    socket.SOL_SOCKET, socket.SO_SNDBUF, self.gateway.limits.max_write_buffer
                )
        self.gateway._opened(self)

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        size = len(data)
        if not self.buffered and size >= 6 + MIN_LENGTH:
            # the common read: one whole request and nothing else, nothing buffered
            # before it: told by its header alone, as the framer would ([TCP] 3.1.3:
            # protocol id 0; [AP] 4.1: a length of 2..254 covering the rest)
            transaction, protocol, length, unit = MBAP_HEADER.unpack_from(data)
            if size == 6 + length and not protocol and length <= MAX_LENGTH:
                if log.isEnabledFor(logging.DEBUG):
                    log.debug("connection %d: RX unit %d: %s", self.id, unit, data.hex(" "))
                self.gateway._request(self, transaction, unit, data[7:])
                if not self.closed:
                    self.live.data(time.monotonic(), False, True)
                return
        framer = self.framer
        framer.receive_data(data)
        request = self.gateway._request
        buffered = self.buffered + len(data)
        completed = False
        while (ev := framer.next_event()) is not None:
            if ev.error is not None:
                self.gateway.counters["bad_headers"] += 1
                log.info("connection %d: bad MBAP header (%s): closed", self.id, ev.error)
                self.close()
                return
            buffered -= len(ev.adu)
            completed = True
            if log.isEnabledFor(logging.DEBUG):
                log.debug("connection %d: RX unit %d: %s", self.id, ev.unit, ev.adu.hex(" "))
            # the request's own fields go back in its answer ([TCP] 3.1.3); its
            # protocol id is 0 (the framer refuses any other: a bad header, above)
            request(self, ev.transaction, ev.unit, ev.pdu)
            if self.closed:
                return
        self.buffered = buffered
        self.live.data(time.monotonic(), buffered > 0, completed)

    def eof_received(self) -> bool | None:
        return None  # close our side too

    def refuse(self) -> None:
        """The gateway's table is full: closed at once (nothing was written to it)."""
        self.closed = True
        assert self.transport is not None
        self.transport.abort()

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
        adu = self.encode(transaction, unit, pdu)
        t.write(self.wire(adu))
        if log.isEnabledFor(logging.DEBUG):
            log.debug("connection %d: TX unit %d: %s", self.id, unit, adu.hex(" "))
        if t.get_write_buffer_size() > self.gateway.limits.max_write_buffer:
            self.gateway.counters["slow_clients"] += 1
            log.info("connection %d does not read its answers: reset", self.id)
            _reset(t)
            self.closed = True  # read none of its requests still in the chunk

    def unsent(self) -> int:
        """Answer bytes written and not yet taken by the client."""
        t = self.transport
        return 0 if t is None else t.get_write_buffer_size()

    def encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
        if 1 <= len(pdu) <= MAX_PDU:  # (the request's own transaction and unit ids)
            return MBAP_HEADER.pack(transaction, 0, len(pdu) + 1, unit) + pdu
        adu: bytes = self.framer.send(transaction, unit, pdu)  # (it says what is wrong)
        return adu

    def wire(self, adu: bytes) -> bytes:
        """The bytes that carry ``adu`` on the connection (TLS records on TLS)."""
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

    def __init__(self, gateway: Owner) -> None:
        super().__init__(gateway)
        self.rtu = _backend.active.Framer("slave", t15=0, t35=0)
        self.timer: asyncio.TimerHandle | None = None

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        now = time.monotonic()
        self.rtu.receive_data(data, now)
        completed = self._events()
        if not self.closed:
            self.live.data(now, not completed, completed)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        super().connection_lost(exc)

    def _on_timer(self) -> None:
        self.timer = None
        if not self.closed:
            now = time.monotonic()
            self.rtu.handle_timer(now)
            if self._events() and not self.closed:
                self.live.data(now, False, True)

    def _events(self) -> bool:
        """Hand the framer's requests to the gateway; True if there was one."""
        # bytes that make no frame yet wait for the framer's flush timeout (a silence)
        self.timer = rearm(self.timer, self.rtu.timer(), self._on_timer)
        completed = False
        while (ev := self.rtu.next_event()) is not None:
            if ev.error is not None:
                self.gateway.counters["rtu_discarded_bytes"] += len(ev.adu)
                continue
            if ev.kind is not FrameKind.REQUEST:
                continue
            completed = True
            if log.isEnabledFor(logging.DEBUG):
                log.debug("connection %d: RX unit %d: %s", self.id, ev.address, ev.adu.hex(" "))
            self.gateway._request(self, 0, ev.address, ev.pdu)
            if self.closed:
                break
        return completed

    def encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
        adu: bytes = _backend.active.add_crc(bytes((unit,)) + pdu)
        self.rtu.send(adu)
        return adu


class _TlsConnection(_Connection):
    """A client of the TLS listener (MODBUS/TCP Security): TLS records through memory
    BIOs around the same MBAP framing.  From its first byte until its handshake is
    done, the connection counts as a request begun: the header timeout ends a
    handshake never finished, and the table's eviction takes it first.  A handshake
    that fails (no client certificate, one the CA did not sign, expired, TLS 1.0/1.1,
    plaintext) is counted and logged once per client and reason, its alert sent, and
    the connection closed; once done, the identity carries the certificate's subject
    and role (`pyrtu.security.tls.peer_identity`)."""

    def __init__(self, gateway: Owner, context: ssl.SSLContext) -> None:
        super().__init__(gateway)
        self.incoming = ssl.MemoryBIO()
        self.outgoing = ssl.MemoryBIO()
        self.tls = context.wrap_bio(self.incoming, self.outgoing, server_side=True)
        self.handshaken = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        if not self.closed:
            self.live.partial_since = self.live.connected  # the handshake: a request begun

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        self.incoming.write(data)
        if not self.handshaken and not self._handshake():
            return
        plain = bytearray()
        ended = False  # the client's close_notify: read() returns b""
        try:
            while chunk := self.tls.read(65536):
                plain += chunk
            ended = True
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            pass
        except ssl.SSLZeroReturnError:
            ended = True
        except ssl.SSLError as exc:  # a renegotiation asked for, a record too long...
            self._flush()
            self.gateway._tls_failed(self, f"TLS: {exc.reason or exc}")
            self.close()
            return
        self._flush()
        if plain:
            super().data_received(bytes(plain))
        if ended and not self.closed:
            self.close()

    def _handshake(self) -> bool:
        """Go on with the handshake; True once it is done (the identity known)."""
        try:
            self.tls.do_handshake()
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            self._flush()
            return False
        except (ssl.SSLError, ValueError) as exc:
            self._flush()  # the alert, when OpenSSL has one to send
            reason = getattr(exc, "reason", None) or str(exc)
            self.gateway._tls_failed(self, f"TLS handshake: {reason}")
            self.close()
            return False
        self._flush()
        who = self.identity
        try:
            self.identity = peer_identity(self.tls, who.address, who.port)
        except (ValueError, TlsSetupError) as exc:  # a certificate cryptography cannot read
            self.gateway._tls_failed(self, f"TLS handshake: unreadable client certificate: {exc}")
            self.close()
            return False
        self.handshaken = True
        self.live.partial_since = None
        return True

    def _flush(self) -> None:
        pending = self.outgoing.read()
        t = self.transport
        if pending and t is not None and not t.is_closing():
            t.write(pending)

    def wire(self, adu: bytes) -> bytes:
        self.tls.write(adu)
        wrapped: bytes = self.outgoing.read()
        return wrapped
