"""`pyrtu.ascii`: Modbus ASCII framing, at the path the documentation shows.

The code lives in `pyrtu.core.ascii`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.core.ascii import *  # noqa: F403
from pyrtu.core.ascii import __all__ as __all__
