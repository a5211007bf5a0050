"""Modbus function codes and their names: a leaf module (it imports nothing of pyrtu).

Application Protocol V1.1b section 5.1 (public function codes) and section 6; the
names are the `pyrtu.Master` methods that send them.
"""

from __future__ import annotations

READ_COILS = 0x01
READ_DISCRETE_INPUTS = 0x02
READ_HOLDING_REGISTERS = 0x03
READ_INPUT_REGISTERS = 0x04
WRITE_SINGLE_COIL = 0x05
WRITE_SINGLE_REGISTER = 0x06
READ_EXCEPTION_STATUS = 0x07
DIAGNOSTICS = 0x08
GET_COMM_EVENT_COUNTER = 0x0B
GET_COMM_EVENT_LOG = 0x0C
WRITE_MULTIPLE_COILS = 0x0F
WRITE_MULTIPLE_REGISTERS = 0x10
REPORT_SERVER_ID = 0x11
READ_FILE_RECORD = 0x14
WRITE_FILE_RECORD = 0x15
MASK_WRITE_REGISTER = 0x16
READ_WRITE_REGISTERS = 0x17
READ_FIFO_QUEUE = 0x18
ENCAPSULATED_INTERFACE = 0x2B
MEI_DEVICE_ID = 0x0E

FUNCTION_NAMES: dict[int, str] = {
    READ_COILS: "read_coils",
    READ_DISCRETE_INPUTS: "read_discrete_inputs",
    READ_HOLDING_REGISTERS: "read_holding_registers",
    READ_INPUT_REGISTERS: "read_input_registers",
    WRITE_SINGLE_COIL: "write_coil",
    WRITE_SINGLE_REGISTER: "write_register",
    READ_EXCEPTION_STATUS: "read_exception_status",
    DIAGNOSTICS: "diagnostics",
    GET_COMM_EVENT_COUNTER: "get_comm_event_counter",
    GET_COMM_EVENT_LOG: "get_comm_event_log",
    WRITE_MULTIPLE_COILS: "write_coils",
    WRITE_MULTIPLE_REGISTERS: "write_registers",
    REPORT_SERVER_ID: "report_server_id",
    READ_FILE_RECORD: "read_file_record",
    WRITE_FILE_RECORD: "write_file_record",
    MASK_WRITE_REGISTER: "mask_write_register",
    READ_WRITE_REGISTERS: "read_write_registers",
    READ_FIFO_QUEUE: "read_fifo_queue",
    ENCAPSULATED_INTERFACE: "read_device_identification",
}


def function_name(function: int) -> str:
    """The method name of a function code (``"function 0x41"`` for others)."""
    return FUNCTION_NAMES.get(function, f"function 0x{function:02X}")


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
