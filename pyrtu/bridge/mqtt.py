"""One MQTT 5 connection on the asyncio loop (paho-mqtt driven by the loop's
reader and writer callbacks, no thread of its own).

`MqttLink.connect` opens a socket (TCP connect and TLS handshake in a worker
thread, so that an unreachable broker never blocks the loop), sends CONNECT with
the last will and waits for CONNACK: `BrokerRefused` when the broker refuses the
client (bad user name or password, not authorized: names the broker and the user,
never the password), `ssl.SSLCertVerificationError` when its certificate does not
verify (never downgraded), `TlsHandshakeFailed` when an ``mqtts://`` broker
breaks off the TLS handshake (a plain MQTT broker does: the hint says so),
OSError when it cannot be reached.  The socket carries TCP_NODELAY
(`pyrtu.tcp.sockets`): a set's read-back reaches the broker at once, not after
the broker's delayed acknowledgement of the previous packet.  Afterwards the
loop reads the socket, writes when paho has bytes queued, and pings every
keepalive; ``on_lost`` is called once when the connection ends.

`dial` is one attempt of an output's connection loop: the back-off waited out, a
link made and connected, its failure sorted into one no retry cures (the output
halts) and one a retry may (reported once per run of failures).

Publications are written at the end of the loop's turn, all of the turn's in one
send; `MqttLink.write_now` writes them at once instead (the bridge's live values:
no timer, no wait for the other tasks of the turn), up to `IMMEDIATE` times a turn,
so that a burst or a backlog still goes in few sends.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode
from paho.mqtt.subscribeoptions import SubscribeOptions

from pyrtu.drivers.reconnect import Reconnect

from ..tcp.sockets import set_nodelay
from .config import MqttConfig

_T = TypeVar("_T")

log = logging.getLogger("pyrtu.bridge")

#: publications written at once in one turn of the loop; more wait for its end
IMMEDIATE = 8

#: CONNACK reason codes that no retry can cure (MQTT 5 3.2.2.2)
FATAL = {
    0x84: "unsupported protocol version",
    0x85: "client identifier not valid",
    0x86: "bad user name or password",
    0x87: "not authorized",
    0x8C: "bad authentication method",
}


class BrokerRefused(ConnectionRefusedError):
    """The broker refused the client's credentials or identity (no retry helps)."""


class TlsHandshakeFailed(ConnectionError):
    """An ``mqtts://`` broker broke off the TLS handshake (reset, end of stream, or
    an answer that is not TLS): most often a plain MQTT broker; retried as any
    connection failure, its message carrying the hint."""


def _handshake_broken(e: BaseException) -> bool:
    """Whether ``e``, raised while connecting over TLS, is the peer breaking off the
    handshake (a refused or unreachable TCP connection is not, nor is a certificate
    that does not verify)."""
    if isinstance(e, ssl.SSLCertVerificationError | ssl.CertificateError):
        return False
    return isinstance(e, ConnectionResetError | BrokenPipeError | ssl.SSLError)


def publish_properties(expiry: int | None = None, correlation: bytes | None = None) -> Properties:
    p = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    if expiry is not None:
        p.MessageExpiryInterval = expiry
    if correlation is not None:
        p.CorrelationData = correlation
    return p


def tls_context(cfg: MqttConfig) -> ssl.SSLContext:
    """The TLS context of an mqtts:// broker: the system's CAs or ``ca``, host
    name checked, an optional client certificate.  OSError/ssl.SSLError if a file
    is unreadable or not PEM."""
    ctx = ssl.create_default_context(cafile=cfg.ca)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if cfg.cert:
        ctx.load_cert_chain(cfg.cert, cfg.key)
    return ctx


class _Coalescing:
    """The client's socket, with its sends gathered: paho writes one packet per
    ``send`` (a system call each); this takes them into a buffer and `drain` hands
    the buffer to the kernel at once, which is what makes thousands of small
    publications a second cheap.  Past ``limit`` unsent bytes it answers as a full
    socket would (BlockingIOError), so paho keeps the rest queued."""

    def __init__(self, sock: Any, limit: int = 1 << 20) -> None:
        self._sock = sock
        self._buf = bytearray()
        self._limit = limit
        self._rbuf = bytearray()
        self.direct = False

    def send(self, data: bytes | bytearray | memoryview) -> int:
        if self.direct:  # closing: what is buffered, then this, straight to the kernel
            self.drain()
            if self._buf:
                raise BlockingIOError
            return int(self._sock.send(data))
        if len(self._buf) >= self._limit:
            raise BlockingIOError
        self._buf += data
        return len(data)

    @property
    def unsent(self) -> int:
        return len(self._buf)

    def recv(self, n: int) -> bytes:
        """paho reads a packet in three small reads: served from one large read."""
        rbuf = self._rbuf
        if not rbuf:
            data = self._sock.recv(65536)  # BlockingIOError when there is nothing
            if not data:
                return b""  # the broker closed the connection
            rbuf += data
        out = bytes(rbuf[:n])
        del rbuf[:n]
        return out

    @property
    def buffered(self) -> int:
        """Bytes read from the socket that paho has not taken yet."""
        return len(self._rbuf)

    def drain(self) -> None:
        """Write what the kernel takes (OSError: the connection failed)."""
        buf = self._buf
        while buf:
            try:
                n = self._sock.send(buf)
            except (BlockingIOError, ssl.SSLWantWriteError, ssl.SSLWantReadError):
                return
            del buf[:n]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


@dataclass(frozen=True)
class Credentials:
    """The password and the TLS context, read once when the bridge starts, so that a
    missing password file or CA is an error then (exit 3), not a retry forever."""

    password: str | None = field(default=None, repr=False)
    tls: ssl.SSLContext | None = None

    @classmethod
    def load(cls, cfg: MqttConfig) -> Credentials:
        """OSError naming the file (password_file, ca, cert, key) that cannot be used."""
        try:
            password = cfg.secret()
        except OSError as e:
            raise OSError(f"password_file {cfg.password_file}: {e.strerror or e}") from None
        try:
            ctx = tls_context(cfg) if cfg.tls else None
        except (OSError, ssl.SSLError) as e:
            names = ", ".join(f"{k} {v}" for k in ("ca", "cert", "key") if (v := getattr(cfg, k)))
            raise OSError(f"TLS files ({names or 'the system CAs'}): {e}") from None
        return cls(password, ctx)


class MqttLink:
    """A connection to the broker (see the module docstring).  Callbacks run on the
    loop: ``on_message(msg)``, ``on_ack(mid)`` (QoS 0: written; QoS 1/2: acknowledged),
    ``on_lost(reason)``."""

    def __init__(
        self,
        cfg: MqttConfig,
        will_topic: str,
        *,
        on_message: Callable[[paho.MQTTMessage], None],
        on_ack: Callable[[int], None],
        on_lost: Callable[[str], None],
        credentials: Credentials | None = None,
        on_refused: Callable[[int, str], None] | None = None,
        will: tuple[bytes, bool] = (b"offline", True),
    ) -> None:
        self.cfg = cfg
        self.will_topic = will_topic
        self.will = will  # (payload, retained), QoS 1
        self.credentials = credentials or Credentials.load(cfg)
        self._on_message = on_message
        self._on_ack = on_ack
        self._on_lost = on_lost
        self._on_refused = on_refused  # (mid, reason): the broker refused it, then on_ack
        self.client: paho.Client | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fd: int | None = None
        self._writing = False
        self._connack: asyncio.Future[tuple[int, str]] | None = None
        self._misc: asyncio.TimerHandle | None = None
        self._out: _Coalescing | None = None
        self._soon = False
        self._turn = 0  # publications written at once in this turn of the loop
        self._q0: deque[tuple[int, paho.MQTTMessageInfo]] = deque()  # QoS 0 not yet written
        self.connected = False

    def _make_client(self) -> paho.Client:
        c = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=self.cfg.client_id,
            protocol=paho.MQTTv5,
            reconnect_on_failure=False,
        )
        if self.cfg.username is not None:
            c.username_pw_set(self.cfg.username, self.credentials.password)
        if self.credentials.tls is not None:
            c.tls_set_context(self.credentials.tls)
        c.will_set(self.will_topic, self.will[0], qos=1, retain=self.will[1])
        c.max_inflight_messages_set(
            0
        )  # our DeliveryWindow bounds it (paho scans its queue per ack)
        c.max_queued_messages_set(0)
        c.suppress_exceptions = False
        c.on_connect = self._connected
        c.on_disconnect = self._disconnected
        # QoS 0 publications are acknowledged once written (`_written`): paho's
        # on_publish would build a reason code and properties for each of them
        c.on_publish = None if self.cfg.qos == 0 else self._published
        c.on_message = self._message
        c.on_socket_open = self._socket_opened
        c.connect_async(self.cfg.host, self.cfg.port, self.cfg.keepalive, clean_start=True)
        return c

    async def connect(self, timeout: float = 10.0) -> None:
        """Connect (see the module docstring); raises on failure, the link closed."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        c = self._make_client()
        self.client = c
        try:
            await self._or_teardown(
                lambda: loop.run_in_executor(None, c.reconnect),
                timeout,
                f"no connection to {self.cfg.broker} within {timeout:g} s",
            )
        except OSError as e:
            if self.credentials.tls is None or not _handshake_broken(e):
                raise
            raise TlsHandshakeFailed(
                f"broker {self.cfg.broker}: TLS handshake failed ({e.strerror or e}): is it a "
                f"plain MQTT broker? then use mqtt://{self.cfg.host}:{self.cfg.port}"
            ) from None
        sock = c.socket()
        if sock is None:
            self._teardown()
            raise ConnectionError(f"{self.cfg.broker}: the connection closed at once")
        self._fd = sock.fileno()
        self._out = _Coalescing(sock)
        c._sock = self._out
        c.on_socket_close = self._socket_closed
        c.on_socket_register_write = self._want_write
        c.on_socket_unregister_write = self._no_write
        loop.add_reader(self._fd, self._readable)
        self._writing = False
        if c.want_write():
            self._want_write(c, None, sock)
        self._connack = connack = loop.create_future()
        self._schedule_misc()
        rc, reason = await self._or_teardown(
            lambda: asyncio.shield(connack),
            timeout,
            f"{self.cfg.broker}: no CONNACK within {timeout:g} s",
        )
        if rc != 0:
            self._teardown()
            user = f"user {self.cfg.username!r}" if self.cfg.username is not None else "anonymous"
            msg = f"broker {self.cfg.broker} refused the connection ({user}): {reason}"
            if rc in FATAL:
                raise BrokerRefused(msg)
            raise ConnectionError(msg)
        self.connected = True

    def subscribe(self, topics: list[str]) -> None:
        """Subscribe (QoS 1) to ``topics``, not receiving our own publications and
        seeing the retain flag as published."""
        assert self.client is not None
        opts = SubscribeOptions(qos=1, noLocal=True, retainAsPublished=True)
        self.client.subscribe([(t, opts) for t in topics])

    def publish(
        self, topic: str, payload: bytes, qos: int, retain: bool, props: Properties | None = None
    ) -> int:
        """Queue a publication; its mid (acknowledged through ``on_ack``), or -1 when
        not connected."""
        c = self.client
        if c is None or not self.connected:
            return -1
        info = c.publish(topic, payload, qos, retain, props)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            return -1
        if qos == 0 and c.on_publish is None:
            self._q0.append((info.mid, info))
        return info.mid

    def _written(self) -> None:
        """QoS 0 publications paho has written (into the socket's buffer): on_ack."""
        q0 = self._q0
        while q0 and q0[0][1].is_published():
            self._on_ack(q0.popleft()[0])

    def close(self, *, graceful: bool = True, with_will: bool = False) -> None:
        """Disconnect (a DISCONNECT first when ``graceful``: the will is not sent,
        unless ``with_will``: reason code 0x04, "Disconnect with Will Message")."""
        c = self.client
        if c is not None and graceful and self.connected and self._fd is not None:
            self.connected = False
            try:
                if self._out is not None:
                    self._out.direct = True
                if with_will:
                    c.disconnect(reasoncode=ReasonCode(PacketTypes.DISCONNECT, identifier=4))
                else:
                    c.disconnect()
                c.loop_write()
            except OSError:
                pass
        self._teardown()

    @property
    def pending_writes(self) -> int:
        """Packets paho holds and bytes not yet written to the socket."""
        c = self.client
        return (0 if c is None else len(c._out_packet)) + (self._out.unsent if self._out else 0)

    # ---------------------------------------------------------------- the loop's side

    async def _or_teardown(
        self, step: Callable[[], Awaitable[_T]], timeout: float, late: str
    ) -> _T:
        """A step of `connect`: ``step()`` awaited within ``timeout`` seconds; when it
        fails the half-made connection is torn down (TimeoutError(``late``) when the
        time ran out)."""
        try:
            return await asyncio.wait_for(step(), timeout)
        except TimeoutError:
            self._teardown()
            raise TimeoutError(late) from None
        except BaseException:
            self._teardown()
            raise

    def _teardown(self) -> None:
        was = self.connected
        self._teardown_quiet()
        if was:
            self._on_lost("closed")

    def _teardown_quiet(self) -> None:
        self.connected = False
        self._q0.clear()  # not written: lost with the connection, as QoS 0 allows
        if self._misc is not None:
            self._misc.cancel()
            self._misc = None
        self._unwatch()
        c, self.client = self.client, None
        if c is not None:
            c.on_socket_close = None
            c.on_disconnect = None
            try:
                c._sock_close()
            except OSError:
                pass
        if self._connack is not None and not self._connack.done():
            self._connack.set_exception(ConnectionError(f"{self.cfg.broker}: connection closed"))
        self._out = None

    def _unwatch(self) -> None:
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
            if self._writing:
                self._loop.remove_writer(self._fd)
            self._writing = False
            self._fd = None

    def _schedule_misc(self) -> None:
        assert self._loop is not None
        self._misc = self._loop.call_later(1.0, self._tick)

    def _tick(self) -> None:
        c = self.client
        if c is None:
            return
        c.loop_misc()
        if self.client is not None:
            self._schedule_misc()

    def _readable(self) -> None:
        c = self.client
        if c is not None:
            c.loop_read()
            # paho stops after a number of packets: what it left in the buffer is not
            # signalled by the socket again
            while self.client is not None and self._out is not None and self._out.buffered:
                if self.client.loop_read() != paho.MQTT_ERR_SUCCESS:
                    break

    def _writable(self) -> None:
        self._soon = False
        self._turn = 0
        c = self.client
        out = self._out
        if c is None or out is None:
            return
        c.loop_write()  # paho's packets into the buffer
        self._written()
        try:
            out.drain()  # one system call for all of them
        except OSError as e:
            log.info("bridge: write to %s failed: %s", self.cfg.broker, e)
            self._lost_now(str(e))
            return
        if out.unsent or c.want_write():  # the kernel's buffer is full: when it has room
            if not self._writing and self._fd is not None and self._loop is not None:
                self._writing = True
                self._loop.add_writer(self._fd, self._writable)
        else:
            self._stop_writing()

    def _want_write(self, client: Any, userdata: Any, sock: Any) -> None:
        # written at the end of this turn of the loop: every publication of the turn
        # in one send, without waiting for select() to say the socket is writable
        if not self._soon and not self._writing and self._loop is not None:
            self._soon = True
            self._loop.call_soon(self._writable)

    def write_now(self) -> None:
        """Write what is queued to the kernel now rather than at the end of the
        loop's turn; past `IMMEDIATE` calls in one turn (or while the kernel's
        buffer is full) it is left for the turn's end.  Acknowledgements of QoS 0
        publications (``on_ack``) come from within this call."""
        c, out, loop = self.client, self._out, self._loop
        if c is None or out is None or loop is None or self._writing:
            return
        if self._turn >= IMMEDIATE:
            return
        self._turn += 1
        if not self._soon:  # the turn's end resets the count
            self._soon = True
            loop.call_soon(self._writable)
        c.loop_write()
        self._written()
        try:
            out.drain()
        except OSError as e:
            log.info("bridge: write to %s failed: %s", self.cfg.broker, e)
            self._lost_now(str(e))

    def _no_write(self, client: Any, userdata: Any, sock: Any) -> None:
        # paho has handed everything over; the buffer may still hold bytes
        if self._out is None or not self._out.unsent:
            self._stop_writing()

    def _stop_writing(self) -> None:
        if self._writing and self._fd is not None and self._loop is not None:
            self._writing = False
            self._loop.remove_writer(self._fd)

    def _lost_now(self, reason: str) -> None:
        was = self.connected
        self._teardown_quiet()
        if was:
            self._on_lost(reason)

    def _socket_opened(self, client: Any, userdata: Any, sock: Any) -> None:
        set_nodelay(sock)  # before CONNECT: see the module docstring

    def _socket_closed(self, client: Any, userdata: Any, sock: Any) -> None:
        self._unwatch()

    def _connected(self, client: Any, userdata: Any, flags: Any, rc: Any, props: Any) -> None:
        code = int(rc.value) if hasattr(rc, "value") else int(rc)
        if self._connack is not None and not self._connack.done():
            self._connack.set_result((code, str(rc)))

    def _disconnected(self, client: Any, userdata: Any, flags: Any, rc: Any, props: Any) -> None:
        if self._connack is not None and not self._connack.done():
            self._connack.set_exception(ConnectionError(f"{self.cfg.broker}: {rc}"))
        if self.connected:
            self.connected = False
            if self._misc is not None:
                self._misc.cancel()
                self._misc = None
            self._unwatch()
            self._on_lost(str(rc))

    def _published(self, client: Any, userdata: Any, mid: int, rc: Any, props: Any) -> None:
        if self._on_refused is not None and getattr(rc, "is_failure", False):
            self._on_refused(mid, f"{rc} (reason code 0x{rc.value:02X})")
        self._on_ack(mid)

    def _message(self, client: Any, userdata: Any, msg: paho.MQTTMessage) -> None:
        self._on_message(msg)


def fatal_error(e: BaseException, broker: str) -> BaseException:
    """What to report of a connection failure no retry cures: a certificate that
    does not verify and other TLS errors as `ConnectionRefusedError` naming the
    broker; `BrokerRefused` (it names the broker) as it is."""
    if isinstance(e, ssl.SSLCertVerificationError):
        return ConnectionRefusedError(
            f"broker {broker}: its certificate does not verify: {e.verify_message or e}"
        )
    if isinstance(e, ssl.SSLError | ssl.CertificateError) and not isinstance(e, BrokerRefused):
        return ConnectionRefusedError(f"broker {broker}: TLS: {e}")
    return e


async def dial(
    make_link: Callable[[], MqttLink],
    reconnect: Reconnect,
    *,
    fatal: Callable[[BaseException], None],
    unreachable: Callable[[BaseException], None],
) -> MqttLink | None:
    """One attempt of an output's connection loop: wait out ``reconnect``'s
    back-off, make a link and connect it; the link when connected, else None after
    telling ``fatal`` (a refusal no retry cures: the credentials, the certificate,
    TLS; as `fatal_error` reports it) or, when the failure begins a run of them
    (`Reconnect.failed`), ``unreachable`` (the broker down, a timeout)."""
    wait = reconnect.wait(time.monotonic())
    if wait > 0:
        await asyncio.sleep(wait)
    link = make_link()
    try:
        await link.connect()
    except (BrokerRefused, ssl.SSLError, ssl.CertificateError) as e:
        fatal(fatal_error(e, link.cfg.broker))
        return None
    except (OSError, TimeoutError, ConnectionError) as e:
        if reconnect.failed(time.monotonic(), e):
            unreachable(e)
        return None
    return link


__all__ = [
    "FATAL",
    "BrokerRefused",
    "Credentials",
    "MqttLink",
    "TlsHandshakeFailed",
    "dial",
    "fatal_error",
    "publish_properties",
    "tls_context",
]
