"""Deprecated path: `pyrtu.functions` (function codes and names).  Each name used here warns
(`DeprecationWarning`) naming its one public path: `pyrtu.pdu.functions`."""

from __future__ import annotations

from pyrtu.core._deprecated import moved
from pyrtu.pdu.functions import __all__ as _HOME

__getattr__ = moved(__name__, "pyrtu.pdu.functions", _HOME)
__all__ = list(_HOME)
