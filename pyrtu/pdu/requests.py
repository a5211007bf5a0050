"""The master's requests: argument checks, the request PDU and the answer's decoder.

One function per `Master` method, shared by the sync `Master`, `pyrtu.drivers.aio.AsyncMaster`
and the poller so that all check arguments (before a byte is sent) and decode answers
identically.  Each returns a `Call`: (slave, request PDU, decoder), the decoder None
when no answer is awaited (a broadcast, FC 08 sub-function 4).

`REQUESTS` is the table of the twenty methods: a `Request` per method name (function
code, whether slave 0 broadcasts, the builder of its `Call` and what is done to the
decoded answer), and for the two that are more than one transaction
(``read_device_identification`` pages, ``execute`` with length rules) a plan: a
generator that yields the Calls (and `Rules` to register first) and returns the
value.  A driver runs a request with `Steps` (sans-I/O: Calls out, answers in) and
gives its caller ``(value, end_time)``; `BY_FUNCTION` finds the poller's reads and
writes by function code.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Generic, NamedTuple, TypeVar

from pyrtu import pdu as pdus
from pyrtu.core.rules import LengthRule
from pyrtu.pdu.errors import FrameError
from pyrtu.pdu.functions import FUNCTION_NAMES


def answer_pdu(pdu: bytes) -> bytes:
    """The decoder of an exchange (`pyrtu.Master.exchange`): the response PDU as it
    came.  The client protocols hand an exception response over through it too, as
    its PDU (function code | 0x80, exception code), instead of raising
    `ExceptionResponseError`."""
    return pdu


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
    s = pdus.check_slave(name, slave, broadcast=False)
    req = pdus.read_request(fc, address, count)
    if fc <= pdus.READ_DISCRETE_INPUTS:
        call = Call(s, req, lambda p: pdus.parse_bits(p, count))
    else:
        call = Call(s, req, lambda p: pdus.parse_registers(p, count))
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


read_coils = _reader(pdus.READ_COILS, "read_coils")
read_discrete_inputs = _reader(pdus.READ_DISCRETE_INPUTS, "read_discrete_inputs")
read_holding_registers = _reader(pdus.READ_HOLDING_REGISTERS, "read_holding_registers")
read_input_registers = _reader(pdus.READ_INPUT_REGISTERS, "read_input_registers")


def _write(slave: int, req: bytes, decode: Callable[[bytes], Any]) -> Call:
    return Call(slave, req, None if slave == 0 else decode)


def write_coil(slave: int, address: int, value: bool) -> Call:
    s = pdus.check_slave("write_coil", slave, broadcast=True)
    req = pdus.write_coil_request(address, value)
    return _write(s, req, lambda p: pdus.parse_echo(p, req))


def write_register(slave: int, address: int, value: int) -> Call:
    s = pdus.check_slave("write_register", slave, broadcast=True)
    req = pdus.write_register_request(address, value)
    return _write(s, req, lambda p: pdus.parse_echo(p, req))


def write_coils(slave: int, address: int, values: Iterable[bool]) -> Call:
    s = pdus.check_slave("write_coils", slave, broadcast=True)
    req = pdus.write_coils_request(address, values)
    return _write(s, req, lambda p: pdus.parse_echo(p, req, 5))


def write_registers(slave: int, address: int, values: Iterable[int]) -> Call:
    s = pdus.check_slave("write_registers", slave, broadcast=True)
    req = pdus.write_registers_request(address, values)
    return _write(s, req, lambda p: pdus.parse_echo(p, req, 5))


def mask_write_register(slave: int, address: int, and_mask: int, or_mask: int) -> Call:
    s = pdus.check_slave("mask_write_register", slave, broadcast=True)
    req = pdus.mask_write_request(address, and_mask, or_mask)
    return _write(s, req, lambda p: pdus.parse_echo(p, req))


def read_write_registers(
    slave: int, read_address: int, read_count: int, write_address: int, values: Iterable[int]
) -> Call:
    s = pdus.check_slave("read_write_registers", slave, broadcast=False)
    req = pdus.read_write_request(read_address, read_count, write_address, values)
    return Call(s, req, lambda p: pdus.parse_registers(p, read_count))


def read_exception_status(slave: int) -> Call:
    s = pdus.check_slave("read_exception_status", slave, broadcast=False)
    return Call(s, bytes((pdus.READ_EXCEPTION_STATUS,)), pdus.parse_exception_status)


def diagnostics(slave: int, sub_function: int, data: int = 0) -> Call:
    s = pdus.check_slave("diagnostics", slave, broadcast=False)
    req = pdus.diagnostics_request(sub_function, data)
    if sub_function == pdus.DIAG_FORCE_LISTEN_ONLY:
        return Call(s, req, None)  # never answered ([SL] 6.4)
    return Call(s, req, lambda p: pdus.parse_diagnostics(p, sub_function))


def get_comm_event_counter(slave: int) -> Call:
    s = pdus.check_slave("get_comm_event_counter", slave, broadcast=False)
    return Call(s, bytes((pdus.GET_COMM_EVENT_COUNTER,)), pdus.parse_event_counter)


def get_comm_event_log(slave: int) -> Call:
    s = pdus.check_slave("get_comm_event_log", slave, broadcast=False)
    return Call(s, bytes((pdus.GET_COMM_EVENT_LOG,)), pdus.parse_event_log)


def report_server_id(slave: int) -> Call:
    s = pdus.check_slave("report_server_id", slave, broadcast=False)
    return Call(s, bytes((pdus.REPORT_SERVER_ID,)), pdus.parse_server_id)


def read_fifo_queue(slave: int, address: int) -> Call:
    s = pdus.check_slave("read_fifo_queue", slave, broadcast=False)
    return Call(s, pdus.fifo_request(address), pdus.parse_fifo)


def read_file_record(slave: int, items: Sequence[tuple[int, int, int]]) -> Call:
    s = pdus.check_slave("read_file_record", slave, broadcast=False)
    req = pdus.read_file_request(items)
    got = list(items)
    return Call(s, req, lambda p: pdus.parse_read_file(p, got))


def write_file_record(slave: int, items: Sequence[tuple[int, int, Sequence[int]]]) -> Call:
    s = pdus.check_slave("write_file_record", slave, broadcast=True)
    req = pdus.write_file_request(items)
    return _write(s, req, lambda p: pdus.parse_echo(p, req))


def device_id_check(slave: int, read_code: int, object_id: int) -> int:
    """read_device_identification's argument checks; returns the slave."""
    s = pdus.check_slave("read_device_identification", slave, broadcast=False)
    pdus.device_id_request(read_code, object_id)
    return s


def device_id_page(slave: int, read_code: int, object_id: int) -> Call:
    return Call(
        slave,
        pdus.device_id_request(read_code, object_id),
        lambda p: pdus.parse_device_id(p, read_code),
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
            pdus.ENCAPSULATED_INTERFACE,
        )
    return int(page.next_object)


def raw_request(slave: int, pdu: bytes, *, name: str = "request") -> Call:
    """Any request PDU (function code + data) -> the response PDU.  Slave 0 broadcasts
    (no answer awaited; the result is b"")."""
    s = pdus.check_slave(name, slave, broadcast=True)
    if not isinstance(pdu, bytes | bytearray | memoryview):
        raise TypeError(f"{name}: pdu must be bytes, not {type(pdu).__name__}")
    raw = bytes(pdu)
    if not raw:
        raise ValueError(f"{name}: pdu is empty (it starts with the function code)")
    if not 1 <= raw[0] <= 127:
        raise ValueError(f"{name}: function must be 1..127, not {raw[0]}")
    if len(raw) > pdus.MAX_PDU:
        raise ValueError(f"{name}: a {len(raw)}-byte PDU exceeds {pdus.MAX_PDU} bytes")
    return Call(s, raw, None if s == 0 else bytes)


def exchange(slave: int, pdu: bytes) -> Call:
    """As `raw_request`, but an exception response is the result too (its PDU, by
    `answer_pdu`: the client protocols do not raise for it)."""
    call = raw_request(slave, pdu, name="exchange")
    return call if call.decode is None else call._replace(decode=answer_pdu)


def execute(
    slave: int,
    function: int,
    data: bytes,
    *,
    request_rule: LengthRule | None = None,
    response_rule: LengthRule | None = None,
) -> Call:
    s = pdus.check_slave(f"function {function}", slave, broadcast=True)
    if isinstance(function, bool) or not isinstance(function, int) or not 1 <= function <= 127:
        raise ValueError(f"execute: function must be 1..127, not {function!r}")
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"execute: data must be bytes, not {type(data).__name__}")
    request = bytes((function,)) + bytes(data)
    if len(request) > pdus.MAX_PDU:
        raise ValueError(f"execute: a {len(request)}-byte PDU exceeds {pdus.MAX_PDU} bytes")
    return Call(s, request, None if s == 0 else (lambda p: p[1:]))


# ------------------------------------------------------------------- the table

T = TypeVar("T")


class Rules(NamedTuple):
    """A plan's step: register length rules for ``function`` before the next Call."""

    function: int
    request_rule: LengthRule | None
    response_rule: LengthRule | None


Plan = Generator[Call | Rules, Any, Any]


@dataclass(frozen=True, slots=True)
class Request(Generic[T]):
    """One master method: ``build(slave, *args) -> Call`` (one transaction), or
    ``plan(slave, *args)`` (several; see the module doc); ``post`` turns the decoded
    answer (None for a broadcast) into the method's value.  ``broadcasting``: slave 0
    is a broadcast in this method (on TCP, unit 0 of the others is the device)."""

    name: str
    function: int
    broadcasting: bool
    build: Callable[..., Call] | None = None
    post: Callable[[Any], T] | None = None
    plan: Callable[..., Plan] | None = None


def _device_id_plan(slave: int, read_code: int = 1, object_id: int = 0) -> Plan:
    s = device_id_check(slave, read_code, object_id)
    out: dict[int, bytes] = {}
    asked: set[int] = set()
    oid: int | None = object_id
    while oid is not None:
        asked.add(oid)
        page = yield device_id_page(s, read_code, oid)
        oid = device_id_next(s, read_code, page, out, asked)
    return out


def _execute_plan(slave: int, function: int, data: bytes = b"", **rules: LengthRule | None) -> Plan:
    """`execute`: its length rules (``request_rule``, ``response_rule``) first."""
    call = execute(slave, function, data, **rules)
    if any(rule is not None for rule in rules.values()):
        yield Rules(function, rules.get("request_rule"), rules.get("response_rule"))
    return (yield call) or b""


def _or(empty: T) -> Callable[[T | None], T]:
    return lambda value: empty if value is None else value


#: the builders of the one-transaction requests, named as the master's methods (their
#: function codes are `pyrtu.pdu.functions.FUNCTION_NAMES`'; those that broadcast to
#: slave 0 are `pyrtu.pdu.BROADCAST_FUNCTIONS`)
_BUILDERS: tuple[Callable[..., Call], ...] = (
    read_coils, read_discrete_inputs, read_holding_registers, read_input_registers,
    write_coil, write_register, write_coils, write_registers, mask_write_register,
    read_write_registers, read_exception_status, diagnostics, get_comm_event_counter,
    get_comm_event_log, report_server_id, read_fifo_queue, read_file_record,
    write_file_record,
)  # fmt: skip
_CODES = {name: code for code, name in FUNCTION_NAMES.items()}
#: what a method returns where its answer is None (FC 08 sub-function 4 is not answered)
_POST: dict[str, Callable[[Any], Any]] = {"diagnostics": _or(0)}


def _entry(build: Callable[..., Call]) -> Request[Any]:
    code = _CODES[build.__name__]
    broadcasting = code in pdus.BROADCAST_FUNCTIONS
    return Request(build.__name__, code, broadcasting, build, _POST.get(build.__name__))


_TABLE: tuple[Request[Any], ...] = (
    Request("request", 0, True, raw_request, _or(b"")),
    Request("exchange", 0, True, exchange, _or(b"")),
    Request("execute", 0, True, plan=_execute_plan),
    *(_entry(build) for build in _BUILDERS),
    Request("read_device_identification", pdus.ENCAPSULATED_INTERFACE, False, plan=_device_id_plan),
)

#: method name -> Request (the twenty methods of `Master` and `AsyncMaster`)
REQUESTS: dict[str, Request[Any]] = {r.name: r for r in _TABLE}
#: function code -> Request, for the one-transaction requests (what the poller sends)
BY_FUNCTION: dict[int, Request[Any]] = {
    r.function: r for r in _TABLE if r.build is not None and r.function
}

#: (slave, broadcasting) -> (the slave the argument checks see, the unit id sent in
#: its place or None): how a transport widens the serial line's 0..247
Address = Callable[[Any, bool], tuple[Any, int | None]]


class Steps:
    """The transactions of one `Request`, sans-I/O: ``next(answer, end)`` takes the
    previous step's answer and end time (None, None at first and after `Rules`) and
    gives the driver the next `Call` (or `Rules` to register), or None when done;
    then `value` is the method's value and `end` when its last answer ended
    (monotonic seconds; when it finished, for one not answered).  A FrameError from
    the plan's own checks (a device pointing back at a page already read) goes to
    ``bad`` (the link's counter) before it is raised."""

    __slots__ = ("_gen", "_post", "_unit", "bad", "end", "value")

    def __init__(
        self, req: Request[Any], slave: Any, args: tuple[Any, ...], kwargs: dict[str, Any],
        address: Address, bad: Callable[[], None],
    ) -> None:  # fmt: skip
        s, self._unit = address(slave, req.broadcasting)
        if req.plan is not None:
            self._gen: Plan = req.plan(s, *args, **kwargs)
        else:
            assert req.build is not None
            self._gen = _single(req.build(s, *args, **kwargs))
        self._post = req.post
        self.bad = bad
        self.value: Any = None
        self.end: float | None = None

    def next(self, answer: Any = None, end: float | None = None) -> Call | Rules | None:
        if end is not None:
            self.end = end
        try:
            step = self._gen.send(answer)
        except StopIteration as stop:
            self.value = stop.value if self._post is None else self._post(stop.value)
            if self.end is None:
                self.end = time.monotonic()
            return None
        except FrameError:
            self.bad()
            raise
        if self._unit is not None and isinstance(step, Call):
            return step._replace(slave=self._unit)
        return step


def call_of(req: Request[Any], slave: Any, args: Any, kwargs: Any, address: Address) -> Call:
    """The Call of a one-transaction request (``req.build``), with the unit id the
    link's ``address`` puts in place of the slave; argument errors raise here."""
    s, unit = address(slave, req.broadcasting)
    call = req.build(s, *args, **kwargs)  # type: ignore[misc]
    return call if unit is None else call._replace(slave=unit)


def _single(call: Call) -> Plan:
    return (yield call)


def serial_address(slave: Any, broadcasting: bool) -> tuple[Any, int | None]:
    """A serial line's addresses: the slave as given (the checks allow 0..247)."""
    return slave, None
