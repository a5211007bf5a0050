"""`pyrtu.functions`: function codes and names, at the path the documentation shows.

The code lives in `pyrtu.pdu.functions`; this module re-exports its public names.
"""

from pyrtu.pdu.functions import (
    DIAGNOSTICS as DIAGNOSTICS,
)
from pyrtu.pdu.functions import (
    ENCAPSULATED_INTERFACE as ENCAPSULATED_INTERFACE,
)
from pyrtu.pdu.functions import (
    FUNCTION_NAMES as FUNCTION_NAMES,
)
from pyrtu.pdu.functions import (
    GET_COMM_EVENT_COUNTER as GET_COMM_EVENT_COUNTER,
)
from pyrtu.pdu.functions import (
    GET_COMM_EVENT_LOG as GET_COMM_EVENT_LOG,
)
from pyrtu.pdu.functions import (
    MASK_WRITE_REGISTER as MASK_WRITE_REGISTER,
)
from pyrtu.pdu.functions import (
    MEI_DEVICE_ID as MEI_DEVICE_ID,
)
from pyrtu.pdu.functions import (
    READ_COILS as READ_COILS,
)
from pyrtu.pdu.functions import (
    READ_DISCRETE_INPUTS as READ_DISCRETE_INPUTS,
)
from pyrtu.pdu.functions import (
    READ_EXCEPTION_STATUS as READ_EXCEPTION_STATUS,
)
from pyrtu.pdu.functions import (
    READ_FIFO_QUEUE as READ_FIFO_QUEUE,
)
from pyrtu.pdu.functions import (
    READ_FILE_RECORD as READ_FILE_RECORD,
)
from pyrtu.pdu.functions import (
    READ_HOLDING_REGISTERS as READ_HOLDING_REGISTERS,
)
from pyrtu.pdu.functions import (
    READ_INPUT_REGISTERS as READ_INPUT_REGISTERS,
)
from pyrtu.pdu.functions import (
    READ_WRITE_REGISTERS as READ_WRITE_REGISTERS,
)
from pyrtu.pdu.functions import (
    REPORT_SERVER_ID as REPORT_SERVER_ID,
)
from pyrtu.pdu.functions import (
    WRITE_FILE_RECORD as WRITE_FILE_RECORD,
)
from pyrtu.pdu.functions import (
    WRITE_MULTIPLE_COILS as WRITE_MULTIPLE_COILS,
)
from pyrtu.pdu.functions import (
    WRITE_MULTIPLE_REGISTERS as WRITE_MULTIPLE_REGISTERS,
)
from pyrtu.pdu.functions import (
    WRITE_SINGLE_COIL as WRITE_SINGLE_COIL,
)
from pyrtu.pdu.functions import (
    WRITE_SINGLE_REGISTER as WRITE_SINGLE_REGISTER,
)
from pyrtu.pdu.functions import (
    function_name as function_name,
)

__all__ = [
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
]
