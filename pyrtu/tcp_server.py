"""`pyrtu.tcp_server`: the Modbus TCP server, at the path the documentation shows.

The code lives in `pyrtu.tcp.server`; this module re-exports its public names.
"""

from pyrtu.tcp.server import (
    UNIT_DIRECT as UNIT_DIRECT,
)
from pyrtu.tcp.server import (
    UNIT_SELF as UNIT_SELF,
)
from pyrtu.tcp.server import (
    Application as Application,
)
from pyrtu.tcp.server import (
    LocalBus as LocalBus,
)
from pyrtu.tcp.server import (
    TcpServer as TcpServer,
)

__all__ = [
    "UNIT_DIRECT",
    "UNIT_SELF",
    "Application",
    "LocalBus",
    "TcpServer",
]
