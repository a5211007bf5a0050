"""The high-rate poller: declared points, coalesced requests, wire-time scheduling.

Layers, sans-I/O up to the driver (time is an input everywhere below `driver`):

============  =================================================================================
`points`      `Point`: name, bus, slave, table, address, type, scale, interval
`config`      `Bus`, `Device`, `PollerConfig`; `load_config` for TOML
`plan`        coalescing: `plan` points into `Block` reads, `Wire` prices them
`schedule`    `BusScheduler`: EDF per bus, writes first, slave health, load
`events`      `Update`, `PortState`, `SlaveState`, `PointDropped`, `Overload`, `TaskFailed`
`driver`      `Poller`: asyncio, one task per bus, ports reopened on back-off
`muxdrive`    the plain ``tcp://`` buses' transactions on one `pyrtu.tcp.mux.TcpMux`
`thread`      `PollerThread`: the poller on a thread of its own, for sync scripts
============  =================================================================================

The rules (coalescing, scheduling, back-off) are in ``docs/POLLER.md``.
"""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

from .config import Bus, ConfigError, Device, PollerConfig, load_config, make_config, parse_config
from .driver import Poller, PollerThread, encode_point
from .events import (
    BusReport,
    Overload,
    PointDropped,
    PortState,
    SlaveState,
    SlaveStats,
    TaskFailed,
    Update,
)
from .masters import AsyncMasterLike, ThreadMaster
from .plan import Block, Cuts, Limits, Wire, merge_pays, plan, split
from .points import TABLES, TYPES, Point, PointError
from .profiles import profile_points
from .schedule import BusScheduler, ScheduledRequest

__all__ = [
    "TABLES",
    "TYPES",
    "AsyncMasterLike",
    "Block",
    "Bus",
    "BusReport",
    "BusScheduler",
    "ConfigError",
    "Cuts",
    "Device",
    "Limits",
    "Overload",
    "Point",
    "PointDropped",
    "PointError",
    "Poller",
    "PollerConfig",
    "PollerThread",
    "PortState",
    "ScheduledRequest",
    "SlaveState",
    "SlaveStats",
    "TaskFailed",
    "ThreadMaster",
    "Update",
    "Wire",
    "encode_point",
    "load_config",
    "make_config",
    "merge_pays",
    "parse_config",
    "plan",
    "profile_points",
    "split",
]

#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(__name__, {"Request": ("pyrtu.poller.schedule", "ScheduledRequest")})
