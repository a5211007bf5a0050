"""PDU constants, data classes and the slave side: request decoders, response encoders.

Imported only by `pyrtu.pdu`, which re-exports every public name here; the slave
(`pyrtu.drivers.slave_base`) reaches the decoders and encoders through `pyrtu.pdu`.
Decoders raise `SlaveException` with the code the specification prescribes: 3 for a
malformed request or a quantity out of range, 2 for an address range running past
0xFFFF (Application Protocol V1.1b, figures of section 6).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

from pyrtu.pdu import functions as fc
from pyrtu.pdu.errors import SlaveException

#: Functions a master may broadcast (slave 0): the writes (Serial Line V1.02, 2.2).
BROADCAST_FUNCTIONS = frozenset(
    {
        fc.WRITE_SINGLE_COIL,
        fc.WRITE_SINGLE_REGISTER,
        fc.WRITE_MULTIPLE_COILS,
        fc.WRITE_MULTIPLE_REGISTERS,
        fc.WRITE_FILE_RECORD,
        fc.MASK_WRITE_REGISTER,
    }
)

# Quantity limits (Application Protocol V1.1b, 6.1-6.17).
MAX_READ_BITS = 2000
MAX_READ_REGISTERS = 125
MAX_WRITE_COILS = 1968
MAX_WRITE_REGISTERS = 123
MAX_RW_READ = 125
MAX_RW_WRITE = 121
MAX_FIFO = 31
MAX_PDU = 253
FILE_REFERENCE_TYPE = 6
MAX_FILE_BYTES = 0xF5
MAX_RECORD = 0x270F

# Diagnostics sub-functions (Serial Line V1.02 / Application Protocol 6.8.1).
DIAG_RETURN_QUERY_DATA = 0x00
DIAG_RESTART_COMMUNICATIONS = 0x01
DIAG_RETURN_DIAGNOSTIC_REGISTER = 0x02
DIAG_CHANGE_ASCII_DELIMITER = 0x03
DIAG_FORCE_LISTEN_ONLY = 0x04
DIAG_CLEAR_COUNTERS = 0x0A
DIAG_BUS_MESSAGE_COUNT = 0x0B
DIAG_BUS_COMM_ERROR_COUNT = 0x0C
DIAG_BUS_EXCEPTION_ERROR_COUNT = 0x0D
DIAG_SLAVE_MESSAGE_COUNT = 0x0E
DIAG_SLAVE_NO_RESPONSE_COUNT = 0x0F
DIAG_SLAVE_NAK_COUNT = 0x10
DIAG_SLAVE_BUSY_COUNT = 0x11
DIAG_BUS_CHAR_OVERRUN_COUNT = 0x12
DIAG_CLEAR_OVERRUN = 0x14

COIL_ON = 0xFF00
COIL_OFF = 0x0000


# ------------------------------------------------------------------ bit packing


def pack_bits(values: Sequence[bool]) -> bytes:
    """Bits LSB first in each byte (Application Protocol 6.1)."""
    out = bytearray((len(values) + 7) // 8)
    for i, v in enumerate(values):
        if v:
            out[i >> 3] |= 1 << (i & 7)
    return bytes(out)


def unpack_bits(data: bytes, count: int) -> list[bool]:
    return [bool(data[i >> 3] >> (i & 7) & 1) for i in range(count)]


#: big-endian 16-bit word unpackers by count, up to the longest PDU's 126 words,
#: from an offset (no slice copy): ``_UNPACK_WORDS_FROM[n](data, offset)``
_UNPACK_WORDS_FROM = [struct.Struct(f">{n}H").unpack_from for n in range(127)]


def _words(data: bytes) -> list[int]:
    n = len(data) // 2
    if n < 127 and len(data) == 2 * n:
        return list(_UNPACK_WORDS_FROM[n](data, 0))
    return list(struct.unpack(f">{n}H", data[: 2 * n]))


def _pack_words(values: Sequence[int]) -> bytes:
    return struct.pack(f">{len(values)}H", *values)


def _BHH(function: int, a: int, b: int) -> bytes:
    return struct.pack(">BHH", function, a, b)


def _u16(data: bytes, at: int) -> int:
    return data[at] << 8 | data[at + 1]


_READ_LIMITS = {
    fc.READ_COILS: MAX_READ_BITS,
    fc.READ_DISCRETE_INPUTS: MAX_READ_BITS,
    fc.READ_HOLDING_REGISTERS: MAX_READ_REGISTERS,
    fc.READ_INPUT_REGISTERS: MAX_READ_REGISTERS,
}


@dataclass(frozen=True)
class CommEventLog:
    """FC 12 answer: ``events`` most recent first (Application Protocol 6.10)."""

    status: int
    event_count: int
    message_count: int
    events: list[int]


@dataclass(frozen=True)
class DeviceIdPage:
    """One FC 43/14 response: ``more_follows`` True when 0xFF."""

    read_code: int
    conformity: int
    more_follows: bool
    next_object: int
    objects: list[tuple[int, bytes]]


# -------------------------------------------------------- requests (slave side)


def _need(pdu: bytes, length: int) -> None:
    if len(pdu) != length:
        raise SlaveException(
            3, f"{fc.function_name(pdu[0])}: request PDU of {len(pdu)} bytes, expected {length}"
        )


def _span_ok(address: int, count: int) -> None:
    if address + count > 0x10000:
        raise SlaveException(2, f"address {address} + {count} runs past 65535")


def decode_read(pdu: bytes) -> tuple[int, int]:
    """FC 01-04 -> (address, count)."""
    _need(pdu, 5)
    address, count = _u16(pdu, 1), _u16(pdu, 3)
    if not 1 <= count <= _READ_LIMITS[pdu[0]]:
        raise SlaveException(3, f"{fc.function_name(pdu[0])}: quantity {count} out of range")
    _span_ok(address, count)
    return address, count


def decode_write_single(pdu: bytes) -> tuple[int, int]:
    """FC 05/06 -> (address, value); FC 05 values other than 0x0000/0xFF00 give 3."""
    _need(pdu, 5)
    address, value = _u16(pdu, 1), _u16(pdu, 3)
    if pdu[0] == fc.WRITE_SINGLE_COIL and value not in (COIL_ON, COIL_OFF):
        raise SlaveException(3, f"write_coil: value 0x{value:04X} is neither 0xFF00 nor 0x0000")
    return address, value


def decode_write_coils(pdu: bytes) -> tuple[int, list[bool]]:
    if len(pdu) < 6:
        raise SlaveException(3, "write_coils: request too short")
    address, count, nbytes = _u16(pdu, 1), _u16(pdu, 3), pdu[5]
    if not 1 <= count <= MAX_WRITE_COILS or nbytes != (count + 7) // 8 or len(pdu) != 6 + nbytes:
        raise SlaveException(3, f"write_coils: quantity {count} / byte count {nbytes} invalid")
    _span_ok(address, count)
    return address, unpack_bits(pdu[6:], count)


def decode_write_registers(pdu: bytes) -> tuple[int, list[int]]:
    if len(pdu) < 6:
        raise SlaveException(3, "write_registers: request too short")
    address, count, nbytes = _u16(pdu, 1), _u16(pdu, 3), pdu[5]
    if not 1 <= count <= MAX_WRITE_REGISTERS or nbytes != 2 * count or len(pdu) != 6 + nbytes:
        raise SlaveException(3, f"write_registers: quantity {count} / byte count {nbytes} invalid")
    _span_ok(address, count)
    return address, _words(pdu[6:])


def decode_mask_write(pdu: bytes) -> tuple[int, int, int]:
    _need(pdu, 7)
    return _u16(pdu, 1), _u16(pdu, 3), _u16(pdu, 5)


def decode_read_write(pdu: bytes) -> tuple[int, int, int, list[int]]:
    if len(pdu) < 10:
        raise SlaveException(3, "read_write_registers: request too short")
    raddr, rcount, waddr, wcount, nbytes = (
        _u16(pdu, 1),
        _u16(pdu, 3),
        _u16(pdu, 5),
        _u16(pdu, 7),
        pdu[9],
    )
    if not 1 <= rcount <= MAX_RW_READ or not 1 <= wcount <= MAX_RW_WRITE:
        raise SlaveException(3, f"read_write_registers: quantities {rcount}/{wcount} out of range")
    if nbytes != 2 * wcount or len(pdu) != 10 + nbytes:
        raise SlaveException(3, f"read_write_registers: byte count {nbytes} for {wcount} registers")
    _span_ok(raddr, rcount)
    _span_ok(waddr, wcount)
    return raddr, rcount, waddr, _words(pdu[10:])


def decode_diagnostics(pdu: bytes) -> tuple[int, int]:
    _need(pdu, 5)
    return _u16(pdu, 1), _u16(pdu, 3)


def decode_fifo(pdu: bytes) -> int:
    _need(pdu, 3)
    return _u16(pdu, 1)


def decode_read_file(pdu: bytes) -> list[tuple[int, int, int]]:
    if len(pdu) < 2 or pdu[1] != len(pdu) - 2 or not 7 <= pdu[1] <= MAX_FILE_BYTES or pdu[1] % 7:
        raise SlaveException(3, "read_file_record: byte count invalid")
    out = []
    for pos in range(2, len(pdu), 7):
        if pdu[pos] != FILE_REFERENCE_TYPE:
            raise SlaveException(2, f"read_file_record: reference type {pdu[pos]}, not 6")
        file, record, length = _u16(pdu, pos + 1), _u16(pdu, pos + 3), _u16(pdu, pos + 5)
        if file == 0 or record > MAX_RECORD or length == 0:
            raise SlaveException(
                2, f"read_file_record: file {file} record {record} length {length}"
            )
        out.append((file, record, length))
    if sum(2 + 2 * n for _f, _r, n in out) > MAX_FILE_BYTES:
        raise SlaveException(3, "read_file_record: the answer would not fit one response")
    return out


def decode_write_file(pdu: bytes) -> list[tuple[int, int, list[int]]]:
    if len(pdu) < 2 or pdu[1] != len(pdu) - 2 or not 9 <= pdu[1] <= MAX_FILE_BYTES:
        raise SlaveException(3, "write_file_record: byte count invalid")
    out = []
    pos = 2
    while pos < len(pdu):
        if pos + 7 > len(pdu):
            raise SlaveException(3, "write_file_record: truncated sub-request")
        if pdu[pos] != FILE_REFERENCE_TYPE:
            raise SlaveException(2, f"write_file_record: reference type {pdu[pos]}, not 6")
        file, record, length = _u16(pdu, pos + 1), _u16(pdu, pos + 3), _u16(pdu, pos + 5)
        end = pos + 7 + 2 * length
        if file == 0 or record > MAX_RECORD or length == 0:
            raise SlaveException(
                2, f"write_file_record: file {file} record {record} length {length}"
            )
        if end > len(pdu):
            raise SlaveException(3, "write_file_record: record data runs past the request")
        out.append((file, record, _words(pdu[pos + 7 : end])))
        pos = end
    return out


def decode_device_id(pdu: bytes) -> tuple[int, int]:
    """FC 43/14 -> (read_code, object_id); other MEI types give exception 1."""
    if len(pdu) < 2 or pdu[1] != fc.MEI_DEVICE_ID:
        raise SlaveException(1, "encapsulated interface: only MEI type 14 is supported")
    _need(pdu, 4)
    if not 1 <= pdu[2] <= 4:
        raise SlaveException(3, f"read_device_identification: read code {pdu[2]} is not 1..4")
    return pdu[2], pdu[3]


# ------------------------------------------------------- responses (slave side)


def bits_response(function: int, values: Sequence[bool]) -> bytes:
    packed = pack_bits(values)
    return bytes((function, len(packed))) + packed


def registers_response(function: int, values: Sequence[int]) -> bytes:
    return bytes((function, 2 * len(values))) + _pack_words(values)


def exception_response(function: int, code: int) -> bytes:
    return bytes((function | 0x80, code))


def diagnostics_response(sub_function: int, data: int) -> bytes:
    return (
        bytes((fc.DIAGNOSTICS,))
        + sub_function.to_bytes(2, "big")
        + (data & 0xFFFF).to_bytes(2, "big")
    )


def event_counter_response(status: int, count: int) -> bytes:
    return (
        bytes((fc.GET_COMM_EVENT_COUNTER,))
        + status.to_bytes(2, "big")
        + (count & 0xFFFF).to_bytes(2, "big")
    )


def event_log_response(log: CommEventLog) -> bytes:
    body = b"".join(
        (x & 0xFFFF).to_bytes(2, "big") for x in (log.status, log.event_count, log.message_count)
    )
    body += bytes(log.events[:64])
    return bytes((fc.GET_COMM_EVENT_LOG, len(body))) + body


def server_id_response(data: bytes) -> bytes:
    return bytes((fc.REPORT_SERVER_ID, len(data))) + data


def fifo_response(values: Sequence[int]) -> bytes:
    body = len(values).to_bytes(2, "big") + _pack_words(values)
    return bytes((fc.READ_FIFO_QUEUE,)) + len(body).to_bytes(2, "big") + body


def read_file_response(records: Sequence[Sequence[int]]) -> bytes:
    body = b"".join(bytes((1 + 2 * len(r), FILE_REFERENCE_TYPE)) + _pack_words(r) for r in records)
    return bytes((fc.READ_FILE_RECORD, len(body))) + body


def device_id_response(page: DeviceIdPage) -> bytes:
    head = bytes(
        (
            fc.ENCAPSULATED_INTERFACE,
            fc.MEI_DEVICE_ID,
            page.read_code,
            page.conformity,
            0xFF if page.more_follows else 0x00,
            page.next_object if page.more_follows else 0,
            len(page.objects),
        )
    )
    return head + b"".join(bytes((oid, len(v))) + v for oid, v in page.objects)
