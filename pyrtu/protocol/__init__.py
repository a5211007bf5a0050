"""The sans-I/O Modbus protocols, public: bytes and times in, actions out.

No port, no clock, no sleep inside: time is an input and the driver does the I/O.
A driver (a thread with ``select``, an asyncio loop, anything that can read and
write bytes and tell the time) asks the protocol for its next action and carries
it out; docs/PROTOCOL.md shows a custom driver for each side.

* client (master): `ClientProtocol.next_action(now)` -> `Send` | `Wait` | `Done`
  (and `Xfer` for a driver that asks: ``next_action(now, xfer=True)``)
* server (slave): `ServerProtocol.next_action(now)` -> `Reply` | `Listen` | `Idle`
"""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

# the client (master) side: one transaction at a time, handed out as actions
from pyrtu.protocol.client import ClientProtocol
from pyrtu.protocol.client_actions import Action, ClientState, Done, Send, Wait, Xfer

# the server (slave) side: requests in, answers out at their time
from pyrtu.protocol.server import (
    Application,
    Idle,
    Listen,
    Reply,
    ServerAction,
    ServerProtocol,
    WatchedApplication,
)

__all__ = [
    "Action",
    "Application",
    "ClientProtocol",
    "ClientState",
    "Done",
    "Idle",
    "Listen",
    "Reply",
    "Send",
    "ServerAction",
    "ServerProtocol",
    "Wait",
    "WatchedApplication",
    "Xfer",
]

#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(
    __name__,
    {
        "State": ("pyrtu.protocol.client_actions", "ClientState"),
        "Exchange": ("pyrtu.protocol.client_actions", "Xfer"),
    },
)
