"""The socket option every TCP socket of pyrtu carries: TCP_NODELAY.

Modbus TCP and MQTT are request and answer: a small write waits for the peer's
answer.  With Nagle's algorithm on, a small write that follows another one not yet
acknowledged is held back until the acknowledgement comes, and the peer delays
its acknowledgement (up to 40 ms on Linux) hoping to carry it on an answer: the
bridge's set round trip took 44 ms this way instead of 3 ms (issue 27.6).  So
every socket pyrtu opens or accepts gets TCP_NODELAY through `set_nodelay`: the
Modbus TCP clients (`pyrtu.tcp`), ``rtu+tcp://``, the gateway's and the TCP
server's accepted connections, and the bridge's MQTT connection.
"""

from __future__ import annotations

import contextlib
import socket
from typing import Any


def set_nodelay(sock: Any) -> bool:
    """Set TCP_NODELAY on ``sock`` (a socket, an SSL socket, or None); whether it is
    set.  A socket that is not TCP (a Unix socket) or already closed is left alone
    (False): the option is an optimisation, never a reason to fail a connection."""
    if sock is None or getattr(sock, "family", None) not in (socket.AF_INET, socket.AF_INET6):
        return False
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return True
    return False


__all__ = ["set_nodelay"]
