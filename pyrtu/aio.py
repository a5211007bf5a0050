"""`pyrtu.aio`: the asyncio master and slave, at the path the documentation shows.

The code lives in `pyrtu.drivers.aio`; this module re-exports its public names.
"""

from pyrtu.drivers.aio import (
    AsyncMaster as AsyncMaster,
)
from pyrtu.drivers.aio import (
    AsyncSlave as AsyncSlave,
)
from pyrtu.drivers.aio import (
    new_event_loop as new_event_loop,
)
from pyrtu.drivers.aio import (
    run as run,
)

__all__ = [
    "AsyncMaster",
    "AsyncSlave",
    "new_event_loop",
    "run",
]
