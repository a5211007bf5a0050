"""Deprecated path: `pyrtu.errors` (pyrtu's exceptions).  Each name used here warns
(`DeprecationWarning`) naming its one public path: ``import pyrtu``'s own name
(`_ROOT`), else `pyrtu.pdu.errors`."""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

#: the names `import pyrtu` has
_ROOT = (
    "EXCEPTION_NAMES",
    "BusFault",
    "ExceptionResponseError",
    "FrameError",
    "ModbusError",
    "NoResponseError",
    "PortError",
    "SlaveException",
)
#: the names only pyrtu.pdu.errors has
_HOME = ("NO_DEVICE_ANSWERED", "PortBusyError", "PureBackendWarning", "exception_name")

__getattr__ = renamed(
    __name__,
    {
        **{name: ("pyrtu", name) for name in _ROOT},
        **{name: ("pyrtu.pdu.errors", name) for name in _HOME},
    },
)
__all__ = [*_ROOT, *_HOME]
