"""Helpers of the Modbus TCP server tests: MBAP ADUs read off a socket whole."""

from __future__ import annotations

import socket
import struct


def read_adu(sock: socket.socket) -> bytes:
    """One whole ADU: the header, then as many bytes as its length field says
    ([TCP] 3.1.3: unit id + PDU).  AssertionError if the server closes first."""
    head = b""
    while len(head) < 6:
        chunk = sock.recv(6 - len(head))
        assert chunk, "the server closed the connection"
        head += chunk
    rest = b""
    (length,) = struct.unpack(">H", head[4:6])
    while len(rest) < length:
        chunk = sock.recv(length - len(rest))
        assert chunk, "the server closed the connection"
        rest += chunk
    return head + rest
