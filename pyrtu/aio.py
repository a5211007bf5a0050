"""`pyrtu.aio`: the asyncio master and slave, at the path the documentation shows.

The code lives in `pyrtu.drivers.aio`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.drivers.aio import *  # noqa: F403
from pyrtu.drivers.aio import __all__ as __all__
