"""`pyrtu.line`: the line object, LineConfig, at the path the documentation shows.

The code lives in `pyrtu.core.line`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.core.line import *  # noqa: F403
from pyrtu.core.line import __all__ as __all__
