"""The master's requests: argument checks, the request PDU and the answer's decoder.

One function per `Master` method, shared by the sync `Master` and `pyrtu.aio.AsyncMaster`
so that both check arguments (before a byte is sent) and decode answers identically.
Each returns a `Call`: (slave, request PDU, decoder), the decoder None when no answer
is awaited (a broadcast, FC 08 sub-function 4).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple

from . import pdu as P
from .errors import FrameError
from .rules import LengthRule


class Call(NamedTuple):
    slave: int
    pdu: bytes
    decode: Callable[[bytes], Any] | None


#: Calls of the reads already checked and built, by (function, slave, address, count):
#: a poller repeats the same few reads, and a Call is immutable.  Only calls whose
#: arguments are exact ints come from here (True == 1 and 1.0 == 1 as keys, but
#: they must fail the checks).
_READS: dict[tuple[int, int, int, int], Call] = {}
_READS_MAX = 4096


def _read(name: str, fc: int, slave: int, address: int, count: int) -> Call:
    s = P.check_slave(name, slave, broadcast=False)
    req = P.read_request(fc, address, count)
    if fc <= P.READ_DISCRETE_INPUTS:
        call = Call(s, req, lambda p: P.parse_bits(p, count))
    else:
        call = Call(s, req, lambda p: P.parse_registers(p, count))
    if type(slave) is type(address) is type(count) is int:
        if len(_READS) >= _READS_MAX:
            _READS.clear()
        _READS[(fc, slave, address, count)] = call
    return call


def _reader(fc: int, name: str) -> Callable[[int, int, int], Call]:
    """The read function of ``fc``: the cached Call of exact-int arguments (checked
    before hashing: unhashable arguments get their named TypeError from `_read`)."""

    def read(slave: int, address: int, count: int) -> Call:
        if type(slave) is type(address) is type(count) is int:
            call = _READS.get((fc, slave, address, count))
            if call is not None:
                return call
        return _read(name, fc, slave, address, count)

    read.__name__ = read.__qualname__ = name
    return read


read_coils = _reader(P.READ_COILS, "read_coils")
read_discrete_inputs = _reader(P.READ_DISCRETE_INPUTS, "read_discrete_inputs")
read_holding_registers = _reader(P.READ_HOLDING_REGISTERS, "read_holding_registers")
read_input_registers = _reader(P.READ_INPUT_REGISTERS, "read_input_registers")


def _write(slave: int, req: bytes, decode: Callable[[bytes], Any]) -> Call:
    return Call(slave, req, None if slave == 0 else decode)


def write_coil(slave: int, address: int, value: bool) -> Call:
    s = P.check_slave("write_coil", slave, broadcast=True)
    req = P.write_coil_request(address, value)
    return _write(s, req, lambda p: P.parse_echo(p, req))


def write_register(slave: int, address: int, value: int) -> Call:
    s = P.check_slave("write_register", slave, broadcast=True)
    req = P.write_register_request(address, value)
    return _write(s, req, lambda p: P.parse_echo(p, req))


def write_coils(slave: int, address: int, values: Iterable[bool]) -> Call:
    s = P.check_slave("write_coils", slave, broadcast=True)
    req = P.write_coils_request(address, values)
    return _write(s, req, lambda p: P.parse_echo(p, req, 5))


def write_registers(slave: int, address: int, values: Iterable[int]) -> Call:
    s = P.check_slave("write_registers", slave, broadcast=True)
    req = P.write_registers_request(address, values)
    return _write(s, req, lambda p: P.parse_echo(p, req, 5))


def mask_write_register(slave: int, address: int, and_mask: int, or_mask: int) -> Call:
    s = P.check_slave("mask_write_register", slave, broadcast=True)
    req = P.mask_write_request(address, and_mask, or_mask)
    return _write(s, req, lambda p: P.parse_echo(p, req))


def read_write_registers(
    slave: int, read_address: int, read_count: int, write_address: int, values: Iterable[int]
) -> Call:
    s = P.check_slave("read_write_registers", slave, broadcast=False)
    req = P.read_write_request(read_address, read_count, write_address, values)
    return Call(s, req, lambda p: P.parse_registers(p, read_count))


def read_exception_status(slave: int) -> Call:
    s = P.check_slave("read_exception_status", slave, broadcast=False)
    return Call(s, bytes((P.READ_EXCEPTION_STATUS,)), P.parse_exception_status)


def diagnostics(slave: int, sub_function: int, data: int = 0) -> Call:
    s = P.check_slave("diagnostics", slave, broadcast=False)
    req = P.diagnostics_request(sub_function, data)
    if sub_function == P.DIAG_FORCE_LISTEN_ONLY:
        return Call(s, req, None)  # never answered ([SL] 6.4)
    return Call(s, req, lambda p: P.parse_diagnostics(p, sub_function))


def get_comm_event_counter(slave: int) -> Call:
    s = P.check_slave("get_comm_event_counter", slave, broadcast=False)
    return Call(s, bytes((P.GET_COMM_EVENT_COUNTER,)), P.parse_event_counter)


def get_comm_event_log(slave: int) -> Call:
    s = P.check_slave("get_comm_event_log", slave, broadcast=False)
    return Call(s, bytes((P.GET_COMM_EVENT_LOG,)), P.parse_event_log)


def report_server_id(slave: int) -> Call:
    s = P.check_slave("report_server_id", slave, broadcast=False)
    return Call(s, bytes((P.REPORT_SERVER_ID,)), P.parse_server_id)


def read_fifo_queue(slave: int, address: int) -> Call:
    s = P.check_slave("read_fifo_queue", slave, broadcast=False)
    return Call(s, P.fifo_request(address), P.parse_fifo)


def read_file_record(slave: int, items: Sequence[tuple[int, int, int]]) -> Call:
    s = P.check_slave("read_file_record", slave, broadcast=False)
    req = P.read_file_request(items)
    got = list(items)
    return Call(s, req, lambda p: P.parse_read_file(p, got))


def write_file_record(slave: int, items: Sequence[tuple[int, int, Sequence[int]]]) -> Call:
    s = P.check_slave("write_file_record", slave, broadcast=True)
    req = P.write_file_request(items)
    return _write(s, req, lambda p: P.parse_echo(p, req))


def device_id_check(slave: int, read_code: int, object_id: int) -> int:
    """read_device_identification's argument checks; returns the slave."""
    s = P.check_slave("read_device_identification", slave, broadcast=False)
    P.device_id_request(read_code, object_id)
    return s


def device_id_page(slave: int, read_code: int, object_id: int) -> Call:
    return Call(
        slave,
        P.device_id_request(read_code, object_id),
        lambda p: P.parse_device_id(p, read_code),
    )


def device_id_next(
    slave: int, read_code: int, page: Any, out: dict[int, bytes], asked: set[int]
) -> int | None:
    """Merge ``page`` into ``out``; the next object id to ask, or None when complete.
    FrameError when the slave points back at an object already read."""
    out.update(page.objects)
    if read_code == 4 or not page.more_follows:
        return None
    if page.next_object in asked:
        raise FrameError(
            f"read_device_identification: slave {slave}: Next Object {page.next_object} "
            "was already read",
            slave,
            P.ENCAPSULATED_INTERFACE,
        )
    return int(page.next_object)


def raw_request(slave: int, pdu: bytes) -> Call:
    """Any request PDU (function code + data) -> the response PDU.  Slave 0 broadcasts
    (no answer awaited; the result is b"")."""
    s = P.check_slave("request", slave, broadcast=True)
    if not isinstance(pdu, bytes | bytearray | memoryview):
        raise TypeError(f"request: pdu must be bytes, not {type(pdu).__name__}")
    raw = bytes(pdu)
    if not raw:
        raise ValueError("request: pdu is empty (it starts with the function code)")
    if not 1 <= raw[0] <= 127:
        raise ValueError(f"request: function must be 1..127, not {raw[0]}")
    if len(raw) > P.MAX_PDU:
        raise ValueError(f"request: a {len(raw)}-byte PDU exceeds {P.MAX_PDU} bytes")
    return Call(s, raw, None if s == 0 else bytes)


def execute(
    slave: int,
    function: int,
    data: bytes,
    request_rule: LengthRule | None,
    response_rule: LengthRule | None,
) -> Call:
    s = P.check_slave(f"function {function}", slave, broadcast=True)
    if isinstance(function, bool) or not isinstance(function, int) or not 1 <= function <= 127:
        raise ValueError(f"execute: function must be 1..127, not {function!r}")
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"execute: data must be bytes, not {type(data).__name__}")
    request = bytes((function,)) + bytes(data)
    if len(request) > P.MAX_PDU:
        raise ValueError(f"execute: a {len(request)}-byte PDU exceeds {P.MAX_PDU} bytes")
    return Call(s, request, None if s == 0 else (lambda p: p[1:]))
