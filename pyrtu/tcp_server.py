"""`pyrtu.tcp_server`: the Modbus TCP server, at the path the documentation shows.

The code lives in `pyrtu.tcp.server`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.tcp.server import *  # noqa: F403
from pyrtu.tcp.server import __all__ as __all__
