"""`pyrtu.tcp_server`: the Modbus TCP server, at the path the documentation shows.

The code lives in `pyrtu.gateway.server`; this module re-exports its public names.
"""

from pyrtu.gateway.server import (
    UNIT_DIRECT as UNIT_DIRECT,
)
from pyrtu.gateway.server import (
    UNIT_SELF as UNIT_SELF,
)
from pyrtu.gateway.server import (
    Application as Application,
)
from pyrtu.gateway.server import (
    LocalBus as LocalBus,
)
from pyrtu.gateway.server import (
    TcpServer as TcpServer,
)

__all__ = [
    "UNIT_DIRECT",
    "UNIT_SELF",
    "Application",
    "LocalBus",
    "TcpServer",
]
