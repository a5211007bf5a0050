"""Deprecated path: `pyrtu.functions` (function codes and names).  Each name used here warns
(`DeprecationWarning`) naming its one public path: `pyrtu.pdu.functions`."""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

#: the names only pyrtu.pdu.functions has
_HOME = (
    "DIAGNOSTICS",
    "ENCAPSULATED_INTERFACE",
    "FUNCTION_NAMES",
    "GET_COMM_EVENT_COUNTER",
    "GET_COMM_EVENT_LOG",
    "MASK_WRITE_REGISTER",
    "MEI_DEVICE_ID",
    "READ_COILS",
    "READ_DISCRETE_INPUTS",
    "READ_EXCEPTION_STATUS",
    "READ_FIFO_QUEUE",
    "READ_FILE_RECORD",
    "READ_HOLDING_REGISTERS",
    "READ_INPUT_REGISTERS",
    "READ_WRITE_REGISTERS",
    "REPORT_SERVER_ID",
    "WRITE_FILE_RECORD",
    "WRITE_MULTIPLE_COILS",
    "WRITE_MULTIPLE_REGISTERS",
    "WRITE_SINGLE_COIL",
    "WRITE_SINGLE_REGISTER",
    "function_name",
)

__getattr__ = renamed(__name__, {name: ("pyrtu.pdu.functions", name) for name in _HOME})
__all__ = list(_HOME)
