"""`pyrtu.functions`: function codes and names, at the path the documentation shows.

The code lives in `pyrtu.pdu.functions`; this module re-exports its public names (its ``__all__``).
"""

from pyrtu.pdu.functions import *  # noqa: F403
from pyrtu.pdu.functions import __all__ as __all__
