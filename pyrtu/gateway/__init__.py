"""A Modbus TCP gateway: many TCP clients onto serial buses (`pyrtu.gateway.gateway`).

`gateway.py` (`Gateway`, `ReopeningBus`, `GatewayLimits`), `_plan.py` (routes and the fair
queue, sans-I/O), `_live.py` (timeouts, eviction), `_conn.py` (one connection),
`_reopen.py` (a bus reopened on back-off), `server.py` (`TcpServer`).
"""

from __future__ import annotations

from pyrtu.gateway.gateway import (
    CLOSE_GRACE,
    HEADER_TIMEOUT,
    IDLE_TIMEOUT,
    MAX_CONNECTIONS,
    MAX_QUEUED_PER_BUS,
    MAX_QUEUED_PER_CONNECTION,
    MAX_WRITE_BUFFER,
    Bus,
    BusEvent,
    FairQueue,
    Gateway,
    GatewayLimits,
    Job,
    QueueFull,
    ReopeningBus,
    Routes,
    close_bus,
    exception_pdu,
    parse_units,
)

__all__ = [
    "CLOSE_GRACE",
    "HEADER_TIMEOUT",
    "IDLE_TIMEOUT",
    "MAX_CONNECTIONS",
    "MAX_QUEUED_PER_BUS",
    "MAX_QUEUED_PER_CONNECTION",
    "MAX_WRITE_BUFFER",
    "Bus",
    "BusEvent",
    "FairQueue",
    "Gateway",
    "GatewayLimits",
    "Job",
    "QueueFull",
    "ReopeningBus",
    "Routes",
    "close_bus",
    "exception_pdu",
    "parse_units",
]
