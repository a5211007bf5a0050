"""Every PDU of the serial function set, with no I/O: the client's side (request
builders, answer parsers: `pyrtu.pdu.client`), the server's (`pyrtu.pdu.base`),
the master's request table (`pyrtu.pdu.requests`), codes and names
(`pyrtu.pdu.functions`), register data (`pyrtu.pdu.data`) and the exceptions
(`pyrtu.pdu.errors`).
"""

from __future__ import annotations

from pyrtu.pdu import client
from pyrtu.pdu.client import *  # noqa: F403  (the names of its __all__)
from pyrtu.pdu.functions import *  # noqa: F403  (the function codes and names)

__all__ = list(client.__all__)
