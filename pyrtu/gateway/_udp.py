"""The gateway's UDP listener (Modbus over UDP): one MBAP ADU per datagram, in and out.

A datagram is a request only when it is exactly one whole valid ADU (protocol id
0, a length field 2..254 that ends the datagram, a function code); anything else
(a bad header, bytes after the ADU, a truncated one, a datagram of pyrtu's answers
sent back) is dropped and counted (``bad_datagrams``): there is no stream to close,
and the listener goes on.

Each client address (host and port) is a `UdpPeer`: a connection of the gateway's
table without a socket of its own.  So everything the gateway does for a TCP client
it does for a UDP one: the access policy decides on its address (`Identity`: the
address and port the datagram came from), its writes go into the audit trail, its
requests have their own queue in the fair queue (0x06 busy past
``max_queued_per_connection``), the idle timeout forgets it (a later datagram makes
it anew), and it counts against ``max_connections`` (a newcomer to a full table
evicts the longest idle UDP peer, else what the gateway's rule picks, else its
datagram is dropped and counted as ``refused``).  Answers go back to the address the
request came from, with its transaction id and unit id ([TCP] 3.1.3); an answer the
socket cannot take at once beyond ``max_write_buffer`` bytes is dropped
(``answers_dropped``), as a client that does not read is reset on TCP.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, cast

from pyrtu.core import _backend
from pyrtu.security.policy import Identity

from ._conn import Owner, _Connection
from ._live import pick_victim

log = logging.getLogger("pyrtu.gateway")


class UdpPeer(_Connection):
    """One client address of a `UdpListener`, in the gateway's connection table."""

    def __init__(self, gateway: Owner, listener: UdpListener, addr: Any) -> None:
        super().__init__(gateway)
        self.listener = listener
        self.addr = addr
        self.identity = Identity(str(addr[0]), int(addr[1]))

    def send(self, transaction: int, unit: int, pdu: bytes) -> None:
        t = self.listener.transport
        if self.closed or t is None or t.is_closing():
            self.gateway.counters["answers_dropped"] += 1
            return
        buffered: int = getattr(t, "get_write_buffer_size", lambda: 0)()
        if buffered > self.gateway.limits.max_write_buffer:
            self.gateway.counters["answers_dropped"] += 1
            log.debug("UDP peer %d: the socket takes no more: answer dropped", self.id)
            return
        adu = self.encode(transaction, unit, pdu)
        t.sendto(adu, self.addr)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("UDP peer %d: TX unit %d: %s", self.id, unit, adu.hex(" "))

    def refuse(self) -> None:
        self.closed = True  # (the table is full: its datagram is dropped)

    def close(self) -> None:
        """Forget the peer (its queued requests are dropped; a later datagram from
        its address makes a new one)."""
        if not self.closed:
            self.closed = True
            self.gateway._closed(self)
        if self.listener.peers.get(self.addr) is self:
            del self.listener.peers[self.addr]


class UdpListener(asyncio.DatagramProtocol):
    """The datagram endpoint of a gateway's UDP listener (see the module docstring)."""

    def __init__(self, gateway: Owner) -> None:
        self.gateway = gateway
        self.transport: asyncio.DatagramTransport | None = None
        self.peers: dict[Any, UdpPeer] = {}
        self.parse = _backend.active.parse_tcp_stream
        self._said_bad = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)  # (3.11's is no subclass)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        frames = self.parse(data, "slave")
        frame = frames[0] if len(frames) == 1 else None
        if frame is None or frame.error is not None or len(frame.adu) != len(data):
            self._bad(data, addr)
            return
        peer = self.peers.get(addr)
        if peer is None or peer.closed:
            self._make_room()
            peer = UdpPeer(self.gateway, self, addr)
            self.gateway._opened(peer)
            if peer.closed:  # refused: the table is full of peers and connections at work
                return
            self.peers[addr] = peer
        if log.isEnabledFor(logging.DEBUG):
            log.debug("UDP peer %d: RX unit %d: %s", peer.id, frame.unit, frame.adu.hex(" "))
        peer.live.data(time.monotonic(), False, True)
        self.gateway._request(peer, frame.transaction, frame.unit, frame.pdu)

    def _make_room(self) -> None:
        """In a full table, a newcomer takes the place of the idlest UDP peer first
        (`pick_victim` among the peers), so that datagrams from ever new addresses
        (easy to forge) do not evict the TCP connections; only when no peer can go
        does the gateway's own rule (`Gateway._opened`) pick among all."""
        gateway = self.gateway
        if len(gateway._connections) < gateway.limits.max_connections:
            return
        victim_id = pick_victim((p.id, p.live, False) for p in self.peers.values())
        if victim_id is None:
            return
        victim = next(p for p in self.peers.values() if p.id == victim_id)
        gateway.counters["evicted"] += 1
        log.info("UDP peer %d (%s) gives way to a new one", victim.id, victim.identity.describe())
        victim.close()

    def _bad(self, data: bytes, addr: Any) -> None:
        self.gateway.counters["bad_datagrams"] += 1
        level = logging.DEBUG if self._said_bad else logging.INFO
        self._said_bad = True
        if log.isEnabledFor(level):
            log.log(
                level,
                "UDP: a datagram of %d bytes from %s:%s is not one Modbus ADU: dropped%s",
                len(data),
                addr[0],
                addr[1],
                "" if level == logging.DEBUG else " (further ones at debug level)",
            )

    def error_received(self, exc: Exception) -> None:
        # (an ICMP error for an answer sent: the client has gone; its peer idles out)
        log.debug("UDP listener: %s", exc)

    def connection_lost(self, exc: Exception | None) -> None:
        for peer in list(self.peers.values()):
            peer.close()

    # what the gateway asks of each of its listeners (as of an asyncio.Server)

    def is_serving(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    async def wait_closed(self) -> None:
        await asyncio.sleep(0)  # (a datagram transport closes at the next turn of the loop)


__all__ = ["UdpListener", "UdpPeer"]
