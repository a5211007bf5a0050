"""Modbus TCP: the clients (`pyrtu.tcp.client`), the sans-I/O client protocol
(`pyrtu.tcp.protocol`), a master's ``tcp://`` links (`pyrtu.tcp.link`), many client
connections behind one descriptor (`pyrtu.tcp.mux`: the poller's) and the socket
options (`pyrtu.tcp.sockets`).
"""

from __future__ import annotations

from pyrtu.tcp import client
from pyrtu.tcp.client import *  # noqa: F403  (the names of its __all__)

__all__ = list(client.__all__)
