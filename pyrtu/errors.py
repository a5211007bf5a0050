"""`pyrtu.errors`: pyrtu's exceptions, at the path the documentation shows.

The code lives in `pyrtu.pdu.errors`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.pdu.errors import *  # noqa: F403
from pyrtu.pdu.errors import __all__ as __all__
