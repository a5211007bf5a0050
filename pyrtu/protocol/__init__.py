"""The sans-I/O Modbus protocols, for drivers of your own (docs/PROTOCOL.md).

No port, no clock, no sleep inside: time is an input and the driver does the I/O.
"""

# the client (master) side: one transaction at a time, handed out as actions
from .._client import ClientProtocol
from .._client_actions import Action, Done, Send, State, Wait

__all__ = ["Action", "ClientProtocol", "Done", "Send", "State", "Wait"]
