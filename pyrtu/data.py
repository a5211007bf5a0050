"""`pyrtu.data`: register data helpers, at the path the documentation shows.

The code lives in `pyrtu.pdu.data`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.pdu.data import *  # noqa: F403
from pyrtu.pdu.data import __all__ as __all__
