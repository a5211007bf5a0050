"""A Modbus TCP gateway: many TCP clients onto serial buses (`pyrtu.gateway.gateway`).

`gateway.py` (`Gateway`, `ReopeningBus`, `GatewayLimits`), `_plan.py` (routes and the fair
queue, sans-I/O), `_live.py` (timeouts, eviction), `_conn.py` (one connection),
`_reopen.py` (a bus reopened on back-off); `TcpServer` lives in `pyrtu.tcp.server`
(`server.py` here is its deprecated old path).
"""

from __future__ import annotations

from pyrtu.core._deprecated import renamed
from pyrtu.gateway import gateway
from pyrtu.gateway.gateway import *  # noqa: F403  (the names of its __all__)

__all__ = list(gateway.__all__)
#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(__name__, {"Bus": ("pyrtu.gateway.gateway", "GatewayBus")})
