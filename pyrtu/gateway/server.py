"""Deprecated path of the Modbus TCP server: it lives in `pyrtu.tcp.server` (with
Modbus TCP), and `pyrtu.tcp_server` re-exports it.  Each name used here warns
(`DeprecationWarning`) naming its new path."""

from __future__ import annotations

from pyrtu.core._deprecated import moved

__getattr__ = moved(
    __name__,
    "pyrtu.tcp.server",
    ["UNIT_DIRECT", "UNIT_SELF", "Application", "LocalBus", "TcpServer"],
)
