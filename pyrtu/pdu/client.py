"""Every PDU of the serial function set: build, check and parse, with no I/O.

A PDU is the function code and its data (Modbus Application Protocol V1.1b,
section 4.1); the ADU adds the address and the CRC (RTU) or the ASCII framing.
Request builders check their arguments and raise ``ValueError`` naming the
function and the reason (`ArgumentTypeError`, a TypeError that is also a
ValueError, for an argument of the wrong type); response parsers raise `FrameError` when the data
cannot be the answer to the request.  The constants, the data classes and the
slave side (request decoders raising `SlaveException`, response encoders) are
defined in `pyrtu.pdu.base` and re-exported here under the same names.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, TypeVar

from pyrtu.pdu import functions
from pyrtu.pdu.base import (
    _BHH,
    _READ_LIMITS,
    _UNPACK_WORDS_FROM,
    BROADCAST_FUNCTIONS,
    COIL_OFF,
    COIL_ON,
    DIAG_BUS_CHAR_OVERRUN_COUNT,
    DIAG_BUS_COMM_ERROR_COUNT,
    DIAG_BUS_EXCEPTION_ERROR_COUNT,
    DIAG_BUS_MESSAGE_COUNT,
    DIAG_CHANGE_ASCII_DELIMITER,
    DIAG_CLEAR_COUNTERS,
    DIAG_CLEAR_OVERRUN,
    DIAG_FORCE_LISTEN_ONLY,
    DIAG_RESTART_COMMUNICATIONS,
    DIAG_RETURN_DIAGNOSTIC_REGISTER,
    DIAG_RETURN_QUERY_DATA,
    DIAG_SLAVE_BUSY_COUNT,
    DIAG_SLAVE_MESSAGE_COUNT,
    DIAG_SLAVE_NAK_COUNT,
    DIAG_SLAVE_NO_RESPONSE_COUNT,
    FILE_REFERENCE_TYPE,
    MAX_FIFO,
    MAX_FILE_BYTES,
    MAX_PDU,
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_RECORD,
    MAX_RW_READ,
    MAX_RW_WRITE,
    MAX_WRITE_COILS,
    MAX_WRITE_REGISTERS,
    CommEventLog,
    DeviceIdPage,
    _pack_words,
    _u16,
    _words,
    bits_response,
    decode_device_id,
    decode_diagnostics,
    decode_fifo,
    decode_mask_write,
    decode_read,
    decode_read_file,
    decode_read_write,
    decode_write_coils,
    decode_write_file,
    decode_write_registers,
    decode_write_single,
    device_id_response,
    diagnostics_response,
    event_counter_response,
    event_log_response,
    exception_response,
    fifo_response,
    pack_bits,
    read_file_response,
    registers_response,
    server_id_response,
    unpack_bits,
)
from pyrtu.pdu.errors import ArgumentTypeError, FrameError
from pyrtu.pdu.functions import *  # noqa: F403  (the function codes and names, re-exported)
from pyrtu.pdu.functions import (
    DIAGNOSTICS,
    ENCAPSULATED_INTERFACE,
    GET_COMM_EVENT_COUNTER,
    GET_COMM_EVENT_LOG,
    MASK_WRITE_REGISTER,
    MEI_DEVICE_ID,
    READ_EXCEPTION_STATUS,
    READ_FIFO_QUEUE,
    READ_FILE_RECORD,
    READ_WRITE_REGISTERS,
    REPORT_SERVER_ID,
    WRITE_FILE_RECORD,
    WRITE_MULTIPLE_COILS,
    WRITE_MULTIPLE_REGISTERS,
    WRITE_SINGLE_COIL,
    WRITE_SINGLE_REGISTER,
    function_name,
)

T = TypeVar("T")

# --------------------------------------------------------------------------- checks


def _int(where: str, name: str, value: object, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ArgumentTypeError(f"{where}: {name} must be an integer, not {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"{where}: {name} must be {lo}..{hi}, not {value}")
    return value


def check_slave(where: str, slave: object, *, broadcast: bool) -> int:
    """A slave address 0..247; 0 (broadcast) only when ``broadcast`` is allowed."""
    s = _int(where, "slave", slave, 0, 247)
    if s == 0 and not broadcast:
        raise ValueError(f"{where}: slave 0 (broadcast) is only for write functions")
    return s


def check_address(where: str, address: object, name: str = "address") -> int:
    return _int(where, name, address, 0, 0xFFFF)


def check_quantity(where: str, count: object, limit: int, name: str = "count") -> int:
    return _int(where, name, count, 1, limit)


def check_span(where: str, address: int, count: int, name: str = "address") -> None:
    if address + count > 0x10000:
        raise ValueError(f"{where}: {name} {address} + {count} runs past 65535")


def check_word(where: str, value: object, name: str = "value") -> int:
    return _int(where, name, value, 0, 0xFFFF)


def _sequence(where: str, values: object, what: str, name: str = "values") -> Iterable[object]:
    """An iterable of items; bytes and str are refused rather than read as numbers
    (``write_registers(1, 0, b'ab')`` would otherwise write 97 and 98)."""
    if isinstance(values, str | bytes | bytearray | memoryview) or not isinstance(values, Iterable):
        raise ArgumentTypeError(
            f"{where}: {name} must be a sequence of {what}, not {type(values).__name__}"
        )
    return values


def check_words(where: str, values: Iterable[object], limit: int) -> list[int]:
    items = _sequence(where, values, "integers 0..65535")
    out = [check_word(where, v, f"values[{i}]") for i, v in enumerate(items)]
    check_quantity(where, len(out), limit, "number of values")
    return out


def check_bits(where: str, values: Iterable[object], limit: int) -> list[bool]:
    out: list[bool] = []
    for i, v in enumerate(_sequence(where, values, "bools")):
        if isinstance(v, bool) or (isinstance(v, int) and v in (0, 1)):
            out.append(bool(v))
        elif isinstance(v, int):
            raise ValueError(f"{where}: values[{i}] must be a bool (or 0/1), not {v!r}")
        else:
            raise ArgumentTypeError(f"{where}: values[{i}] must be a bool (or 0/1), not {v!r}")
    check_quantity(where, len(out), limit, "number of values")
    return out


# ------------------------------------------------------------ requests (master)


def read_request(function: int, address: int, count: int) -> bytes:
    """FC 01-04: address and quantity."""
    limit = _READ_LIMITS[function]
    fast = type(address) is int and type(count) is int  # bool excluded
    if not (fast and 0 <= address and 1 <= count <= limit and address + count <= 0x10000):
        where = function_name(function)
        check_address(where, address)
        check_quantity(where, count, limit)
        check_span(where, address, count)
    return _BHH(function, address, count)


def write_coil_request(address: int, value: object) -> bytes:
    where = "write_coil"
    check_address(where, address)
    (bit,) = check_bits(where, [value], 1)
    return _BHH(WRITE_SINGLE_COIL, address, COIL_ON if bit else COIL_OFF)


def write_register_request(address: int, value: int) -> bytes:
    where = "write_register"
    check_address(where, address)
    check_word(where, value)
    return _BHH(WRITE_SINGLE_REGISTER, address, value)


def _written(
    where: str, address: int, values: Iterable[object], check: Callable[..., list[T]], limit: int
) -> list[T]:
    """The values of a multiple write (FC 15, FC 16) checked by ``check`` (`check_bits`,
    `check_words`) after the start address, then the span they cover."""
    check_address(where, address)
    items = check(where, values, limit)
    check_span(where, address, len(items))
    return items


def write_coils_request(address: int, values: Iterable[object]) -> bytes:
    bits = _written("write_coils", address, values, check_bits, MAX_WRITE_COILS)
    packed = pack_bits(bits)
    return _BHH(WRITE_MULTIPLE_COILS, address, len(bits)) + bytes((len(packed),)) + packed


def write_registers_request(address: int, values: Iterable[int]) -> bytes:
    words = _written("write_registers", address, values, check_words, MAX_WRITE_REGISTERS)
    n = len(words)
    return _BHH(WRITE_MULTIPLE_REGISTERS, address, n) + bytes((2 * n,)) + _pack_words(words)


def mask_write_request(address: int, and_mask: int, or_mask: int) -> bytes:
    where = "mask_write_register"
    check_address(where, address)
    check_word(where, and_mask, "and_mask")
    check_word(where, or_mask, "or_mask")
    return struct.pack(">BHHH", MASK_WRITE_REGISTER, address, and_mask, or_mask)


def read_write_request(
    read_address: int, read_count: int, write_address: int, values: Iterable[int]
) -> bytes:
    where = "read_write_registers"
    check_address(where, read_address, "read_address")
    check_quantity(where, read_count, MAX_RW_READ, "read_count")
    check_span(where, read_address, read_count, "read_address")
    check_address(where, write_address, "write_address")
    words = check_words(where, values, MAX_RW_WRITE)
    check_span(where, write_address, len(words), "write_address")
    n = len(words)
    head = struct.pack(
        ">BHHHHB", READ_WRITE_REGISTERS, read_address, read_count, write_address, n, 2 * n
    )
    return head + _pack_words(words)


def diagnostics_request(sub_function: int, data: int = 0) -> bytes:
    where = "diagnostics"
    _int(where, "sub_function", sub_function, 0, 0xFFFF)
    check_word(where, data, "data")
    return _BHH(DIAGNOSTICS, sub_function, data)


def fifo_request(address: int) -> bytes:
    check_address("read_fifo_queue", address)
    return bytes((READ_FIFO_QUEUE,)) + address.to_bytes(2, "big")


def _file_items(where: str, items: object, third: str) -> Iterator[tuple[int, Any, Any, Any]]:
    """``(i, file, record, third)`` of each FC 20/21 sub-request, its file number
    (1..65535) and record number (0..9999) checked; the third field is the caller's."""
    shape = f"(file, record, {third})"
    for i, item in enumerate(_sequence(where, items, shape, "items")):
        if not isinstance(item, tuple | list):
            raise ArgumentTypeError(f"{where}: item {i} must be {shape}, not {item!r}")
        if len(item) != 3:
            raise ValueError(f"{where}: item {i} must be {shape}, not {item!r}")
        file, record, value = item
        _int(where, f"item {i} file", file, 1, 0xFFFF)
        _int(where, f"item {i} record", record, 0, MAX_RECORD)
        yield i, file, record, value


def read_file_request(items: Iterable[tuple[int, int, int]]) -> bytes:
    """FC 20: ``[(file, record, length), ...]``; the answer must fit one PDU."""
    where = "read_file_record"
    body = bytearray()
    answer = 0
    for i, file, record, length in _file_items(where, items, "length"):
        _int(where, f"item {i} length", length, 1, (MAX_FILE_BYTES - 2) // 2)
        body += struct.pack(">BHHH", FILE_REFERENCE_TYPE, file, record, length)
        answer += 2 + 2 * length
    if not body:
        raise ValueError(f"{where}: give at least one (file, record, length)")
    if len(body) > MAX_FILE_BYTES:
        raise ValueError(f"{where}: {len(body) // 7} sub-requests do not fit one request")
    if answer > MAX_FILE_BYTES:
        raise ValueError(f"{where}: the answer ({answer} bytes) would not fit one response (245)")
    return bytes((READ_FILE_RECORD, len(body))) + bytes(body)


def write_file_request(items: Iterable[tuple[int, int, Sequence[int]]]) -> bytes:
    """FC 21: ``[(file, record, values), ...]``."""
    where = "write_file_record"
    body = bytearray()
    for _, file, record, values in _file_items(where, items, "values"):
        words = check_words(where, values, (MAX_FILE_BYTES - 7) // 2)
        body += struct.pack(">BHHH", FILE_REFERENCE_TYPE, file, record, len(words))
        body += _pack_words(words)
    if not body:
        raise ValueError(f"{where}: give at least one (file, record, values)")
    if len(body) > MAX_FILE_BYTES:
        raise ValueError(f"{where}: {len(body)} bytes of sub-requests do not fit one request (245)")
    return bytes((WRITE_FILE_RECORD, len(body))) + bytes(body)


def device_id_request(read_code: int, object_id: int) -> bytes:
    where = "read_device_identification"
    _int(where, "read_code", read_code, 1, 4)
    _int(where, "object_id", object_id, 0, 255)
    return bytes((ENCAPSULATED_INTERFACE, MEI_DEVICE_ID, read_code, object_id))


# ----------------------------------------------------------- responses (master)


def _frame_error(function: int, message: str) -> FrameError:
    return FrameError(f"{function_name(function)}: {message}", function=function)


def _expect_len(function: int, pdu: bytes, length: int) -> None:
    if len(pdu) != length:
        raise _frame_error(function, f"response PDU has {len(pdu)} bytes, expected {length}")


def parse_bits(pdu: bytes, count: int) -> list[bool]:
    fc = pdu[0]
    nbytes = (count + 7) // 8
    _expect_len(fc, pdu, 2 + nbytes)
    if pdu[1] != nbytes:
        raise _frame_error(fc, f"byte count {pdu[1]}, expected {nbytes} for {count} bits")
    return unpack_bits(pdu[2:], count)


def parse_registers(pdu: bytes, count: int) -> list[int]:
    if len(pdu) == 2 + 2 * count and pdu[1] == 2 * count and count < 127:  # the answer
        return list(_UNPACK_WORDS_FROM[count](pdu, 2))
    fc = pdu[0]
    _expect_len(fc, pdu, 2 + 2 * count)
    if pdu[1] != 2 * count:
        raise _frame_error(fc, f"byte count {pdu[1]}, expected {2 * count} for {count} registers")
    return _words(pdu[2:])


def parse_echo(pdu: bytes, request: bytes, length: int | None = None) -> None:
    """FC 05/06/08/21/22 echo the request; FC 15/16 echo its first 5 bytes."""
    want = request if length is None else request[:length]
    if pdu != want:
        raise _frame_error(
            request[0], f"response {pdu.hex(' ')} does not echo the request {want.hex(' ')}"
        )


def parse_exception_status(pdu: bytes) -> int:
    _expect_len(READ_EXCEPTION_STATUS, pdu, 2)
    return pdu[1]


def parse_diagnostics(pdu: bytes, sub_function: int) -> int:
    _expect_len(DIAGNOSTICS, pdu, 5)
    if _u16(pdu, 1) != sub_function:
        raise _frame_error(
            DIAGNOSTICS, f"sub-function {_u16(pdu, 1)} in the response, sent {sub_function}"
        )
    return _u16(pdu, 3)


def parse_event_counter(pdu: bytes) -> tuple[int, int]:
    _expect_len(GET_COMM_EVENT_COUNTER, pdu, 5)
    return _u16(pdu, 1), _u16(pdu, 3)


def parse_event_log(pdu: bytes) -> CommEventLog:
    fc = GET_COMM_EVENT_LOG
    if len(pdu) < 8 or pdu[1] != len(pdu) - 2 or pdu[1] > 6 + 64:
        raise _frame_error(fc, f"malformed event log {pdu.hex(' ')}")
    return CommEventLog(_u16(pdu, 2), _u16(pdu, 4), _u16(pdu, 6), list(pdu[8:]))


def parse_server_id(pdu: bytes) -> bytes:
    """FC 17: the data after the byte count (server ID, run indicator, extra data)."""
    if len(pdu) < 2 or pdu[1] != len(pdu) - 2:
        raise _frame_error(REPORT_SERVER_ID, f"byte count does not match in {pdu.hex(' ')}")
    return pdu[2:]


def parse_fifo(pdu: bytes) -> list[int]:
    fc = READ_FIFO_QUEUE
    if len(pdu) < 5 or _u16(pdu, 1) != len(pdu) - 3:
        raise _frame_error(fc, f"byte count does not match in {pdu.hex(' ')}")
    count = _u16(pdu, 3)
    if count > MAX_FIFO or len(pdu) != 5 + 2 * count:
        raise _frame_error(fc, f"FIFO count {count} does not match {len(pdu) - 5} data bytes")
    return _words(pdu[5:])


def parse_read_file(pdu: bytes, items: Sequence[tuple[int, int, int]]) -> list[list[int]]:
    fc = READ_FILE_RECORD
    if len(pdu) < 2 or pdu[1] != len(pdu) - 2:
        raise _frame_error(fc, f"response data length does not match in {pdu.hex(' ')}")
    out: list[list[int]] = []
    pos = 2
    for _file, _record, length in items:
        end = pos + 2 + 2 * length
        if end > len(pdu) or pdu[pos] != 1 + 2 * length or pdu[pos + 1] != FILE_REFERENCE_TYPE:
            raise _frame_error(
                fc, f"sub-response {len(out)} is malformed (expected {length} registers)"
            )
        out.append(_words(pdu[pos + 2 : pos + 2 + 2 * length]))
        pos += 2 + 2 * length
    if pos != len(pdu):
        raise _frame_error(fc, f"{len(pdu) - pos} bytes after the last sub-response")
    return out


def parse_device_id(pdu: bytes, read_code: int) -> DeviceIdPage:
    fc = ENCAPSULATED_INTERFACE
    if len(pdu) < 7 or pdu[1] != MEI_DEVICE_ID:
        raise _frame_error(fc, f"not a device identification response: {pdu.hex(' ')}")
    if pdu[2] != read_code:
        raise _frame_error(fc, f"read code {pdu[2]} in the response, sent {read_code}")
    if pdu[4] not in (0x00, 0xFF):
        raise _frame_error(fc, f"More Follows is 0x{pdu[4]:02X}, not 0x00 or 0xFF")
    objects: list[tuple[int, bytes]] = []
    pos = 7
    for _ in range(pdu[6]):
        if pos + 2 > len(pdu) or pos + 2 + pdu[pos + 1] > len(pdu):
            raise _frame_error(fc, f"object list runs past the response ({pdu[6]} objects)")
        objects.append((pdu[pos], pdu[pos + 2 : pos + 2 + pdu[pos + 1]]))
        pos += 2 + pdu[pos + 1]
    if pos != len(pdu):
        raise _frame_error(fc, f"{len(pdu) - pos} bytes after the last object")
    return DeviceIdPage(pdu[2], pdu[3], pdu[4] == 0xFF, pdu[5], objects)


__all__ = [
    "BROADCAST_FUNCTIONS",
    "COIL_OFF",
    "COIL_ON",
    "DIAG_BUS_CHAR_OVERRUN_COUNT",
    "DIAG_BUS_COMM_ERROR_COUNT",
    "DIAG_BUS_EXCEPTION_ERROR_COUNT",
    "DIAG_BUS_MESSAGE_COUNT",
    "DIAG_CHANGE_ASCII_DELIMITER",
    "DIAG_CLEAR_COUNTERS",
    "DIAG_CLEAR_OVERRUN",
    "DIAG_FORCE_LISTEN_ONLY",
    "DIAG_RESTART_COMMUNICATIONS",
    "DIAG_RETURN_DIAGNOSTIC_REGISTER",
    "DIAG_RETURN_QUERY_DATA",
    "DIAG_SLAVE_BUSY_COUNT",
    "DIAG_SLAVE_MESSAGE_COUNT",
    "DIAG_SLAVE_NAK_COUNT",
    "DIAG_SLAVE_NO_RESPONSE_COUNT",
    "FILE_REFERENCE_TYPE",
    "MAX_FIFO",
    "MAX_FILE_BYTES",
    "MAX_PDU",
    "MAX_READ_BITS",
    "MAX_READ_REGISTERS",
    "MAX_RECORD",
    "MAX_RW_READ",
    "MAX_RW_WRITE",
    "MAX_WRITE_COILS",
    "MAX_WRITE_REGISTERS",
    "ArgumentTypeError",
    "CommEventLog",
    "DeviceIdPage",
    "bits_response",
    "check_address",
    "check_bits",
    "check_quantity",
    "check_slave",
    "check_span",
    "check_word",
    "check_words",
    "decode_device_id",
    "decode_diagnostics",
    "decode_fifo",
    "decode_mask_write",
    "decode_read",
    "decode_read_file",
    "decode_read_write",
    "decode_write_coils",
    "decode_write_file",
    "decode_write_registers",
    "decode_write_single",
    "device_id_request",
    "device_id_response",
    "diagnostics_request",
    "diagnostics_response",
    "event_counter_response",
    "event_log_response",
    "exception_response",
    "fifo_request",
    "fifo_response",
    "mask_write_request",
    "pack_bits",
    "parse_bits",
    "parse_device_id",
    "parse_diagnostics",
    "parse_echo",
    "parse_event_counter",
    "parse_event_log",
    "parse_exception_status",
    "parse_fifo",
    "parse_read_file",
    "parse_registers",
    "parse_server_id",
    "read_file_request",
    "read_file_response",
    "read_request",
    "read_write_request",
    "registers_response",
    "server_id_response",
    "unpack_bits",
    "write_coil_request",
    "write_coils_request",
    "write_file_request",
    "write_register_request",
    "write_registers_request",
]
__all__ += functions.__all__
