"""`pyrtu.errors`: pyrtu's exceptions, at the path the documentation shows.

The code lives in `pyrtu.pdu.errors`; this module re-exports its public names.
"""

from pyrtu.pdu.errors import (
    EXCEPTION_NAMES as EXCEPTION_NAMES,
)
from pyrtu.pdu.errors import (
    BusFault as BusFault,
)
from pyrtu.pdu.errors import (
    ExceptionResponseError as ExceptionResponseError,
)
from pyrtu.pdu.errors import (
    FrameError as FrameError,
)
from pyrtu.pdu.errors import (
    ModbusError as ModbusError,
)
from pyrtu.pdu.errors import (
    NoResponseError as NoResponseError,
)
from pyrtu.pdu.errors import (
    PortError as PortError,
)
from pyrtu.pdu.errors import (
    SlaveException as SlaveException,
)
from pyrtu.pdu.errors import (
    exception_name as exception_name,
)

__all__ = [
    "EXCEPTION_NAMES",
    "BusFault",
    "ExceptionResponseError",
    "FrameError",
    "ModbusError",
    "NoResponseError",
    "PortError",
    "SlaveException",
    "exception_name",
]
