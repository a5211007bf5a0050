"""The sans-I/O Modbus protocols, public: bytes and times in, actions out.

A driver (a thread with ``select``, an asyncio loop, anything that can read and
write bytes and tell the time) asks the protocol for its next action and carries
it out; docs/PROTOCOL.md shows a custom driver for each.
"""

from __future__ import annotations

# -- the server (slave) protocol: ServerProtocol.next_action(now) -> ServerAction
from .._server import Application, Idle, Listen, Reply, ServerAction, ServerProtocol

__all__ = [
    # server
    "Application",
    "Idle",
    "Listen",
    "Reply",
    "ServerAction",
    "ServerProtocol",
]
