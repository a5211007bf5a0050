"""Modbus TCP: the clients (`pyrtu.tcp.client`), the sans-I/O client protocol
(`pyrtu.tcp.protocol`), a master's ``tcp://`` links (`pyrtu.tcp.link`) and the socket
options (`pyrtu.tcp.sockets`).
"""

from __future__ import annotations

from pyrtu.tcp.client import (
    DEFAULT_PORT,
    AsyncTcpClient,
    TcpClient,
    parse_tcp_url,
    rtu_over_tcp,
)

__all__ = [
    "DEFAULT_PORT",
    "AsyncTcpClient",
    "TcpClient",
    "parse_tcp_url",
    "rtu_over_tcp",
]
