"""The Modbus master (client) over a serial line, RTU or ASCII.

::

    with pyrtu.Master("/dev/ttyUSB0", 19200, parity="E", timeout=0.5) as bus:
        speed, current = bus.read_holding_registers(1, 2, 2)
        bus.write_register(3, 683, 0x1000)

One transaction at a time per bus (a lock makes the object thread-safe).  A
transaction: flush stale input, wait the inter-frame silence (t3.5 after the
end of the last frame on the wire, measured from when transmission actually
ended and from the last byte received; ``t35=0`` turns it off), send, read
back the echo (``echo=True``), then feed what arrives to the sans-I/O framer
until the answer is complete: a response is recognised by its length as soon
as its last byte is in, without waiting for a timeout.

Frames that are not the answer (another slave, another function, data that
does not fit the request, frames that ended before the request was sent) are
dropped and counted; the wait goes on for a short settling time in case the
real answer follows, then the transaction ends with a `FrameError`.  Nothing
valid within ``timeout`` after the end of transmission: `NoResponseError`.
Exception responses return at once as `ExceptionResponseError`.  ``retries``
repeats a transaction after `NoResponseError` and `FrameError` (not after an
exception response).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Sequence
from typing import Any

from . import _backend
from . import pdu as P
from ._master_io import Transactions, _counters
from .ascii import AsciiFramer
from .errors import FrameError
from .port import Port, open_port
from .rules import LengthRule, RuleTable, check_rules


def _mode(mode: str) -> str:
    if mode not in ("rtu", "ascii"):
        raise ValueError(f"mode must be 'rtu' or 'ascii', not {mode!r}")
    return mode


def _seconds(name: str, value: object, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or value != value:
        raise ValueError(f"{name} must be a number of seconds, not {value!r}")
    if value < 0 or (positive and value == 0):
        raise ValueError(
            f"{name} must be {'positive' if positive else 'non-negative'}, not {value!r}"
        )
    return float(value)


class Master(Transactions):
    """A Modbus master on one serial line (see the module docstring)."""

    def __init__(
        self,
        port: Any,
        baudrate: int = 19200,
        parity: str = "E",
        stopbits: float = 1,
        bytesize: int = 8,
        timeout: float = 1.0,
        retries: int = 0,
        mode: str = "rtu",
        echo: bool = False,
        rs485: Any = None,
        *,
        t15: float | None = None,
        t35: float | None = None,
        timing: str = "modbus",
        broadcast_delay: float = 0.1,
        rules: RuleTable | None = None,
        max_adu: int = 256,
        strict: bool = False,
        backend: str | None = None,
        exclusive: bool = True,
    ) -> None:
        self.mode = _mode(mode)
        self.timeout = _seconds("timeout", timeout, positive=True)
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise ValueError(f"retries must be a non-negative integer, not {retries!r}")
        self.retries = retries
        self.broadcast_delay = _seconds("broadcast_delay", broadcast_delay)
        self.echo = bool(echo)
        self._backend = _backend.backend(backend)
        self._rules = dict(check_rules(rules))
        self._max_adu = max_adu
        self._strict = strict
        self._timing_rule = timing
        self._t15 = t15
        self._t35_arg = t35
        # Check every option before the port is opened.
        self._framer_args: dict[str, Any] = {}
        self._make_framer(baudrate, parity, stopbits, bytesize)
        self.port: Port = open_port(
            port,
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            bytesize=bytesize,
            rs485=rs485,
            exclusive=exclusive,
        )
        p = self.port
        timing_ = self._make_framer(p.baudrate, p.parity, p.stopbits, p.bytesize)
        #: the inter-frame silence the master keeps before a request (seconds; 0: none)
        self.t35 = timing_ if self.mode == "rtu" else 0.0
        self._settle = max(0.02, 3 * self.t35)
        self._check_crc = self._backend.check_crc
        self._lock = threading.RLock()
        self._counters = _counters()
        self._tx_end = 0.0
        self._last_rx = 0.0
        self._quiet_until = 0.0

    # ----------------------------------------------------------------- set-up

    def _make_framer(self, baudrate: int, parity: str, stopbits: float, bytesize: int) -> float:
        be = self._backend
        args: dict[str, Any] = dict(
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            bytesize=bytesize,
            timing=self._timing_rule,
            t15=self._t15,
            t35=self._t35_arg,
            strict=self._strict,
            max_adu=self._max_adu,
        )
        self._framer_args = args
        self._framer: Any = (
            be.Framer("master", rules=self._rules, **args)
            if self.mode == "rtu"
            else AsciiFramer("master")
        )
        return float(
            be.char_timing(
                baudrate, parity, stopbits, bytesize, self._timing_rule, self._t15, self._t35_arg
            ).t35
        )

    def add_rule(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        """Register length rules for a (vendor) function code in the framer."""
        new = check_rules({function: (request_rule, response_rule)})
        with self._lock:
            if self._rules.get(function) != new[function]:
                self._rules.update(new)
                if self.mode == "rtu":
                    self._framer = self._backend.Framer(
                        "master", rules=self._rules, **self._framer_args
                    )

    @property
    def counters(self) -> dict[str, int]:
        """requests, responses, broadcasts, exceptions, timeouts, crc_errors, frame_errors,
        echo_mismatches, retries, discarded bytes (total and per reason)."""
        with self._lock:
            return dict(self._counters)

    def close(self) -> None:
        """Close the port (a pyserial object passed in is left open)."""
        with self._lock:
            self.port.close()

    def __enter__(self) -> Master:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<pyrtu.Master {self.port.name} {self.mode} {self.port.baudrate} baud>"

    # ---------------------------------------------------------------- bit/word access

    def read_coils(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 01: ``count`` coils from ``address``."""
        s = P.check_slave("read_coils", slave, broadcast=False)
        req = P.read_request(P.READ_COILS, address, count)
        return self._call(s, req, lambda p: P.parse_bits(p, count), 5 + (count + 7) // 8)

    def read_discrete_inputs(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 02."""
        s = P.check_slave("read_discrete_inputs", slave, broadcast=False)
        req = P.read_request(P.READ_DISCRETE_INPUTS, address, count)
        return self._call(s, req, lambda p: P.parse_bits(p, count), 5 + (count + 7) // 8)

    def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 03."""
        s = P.check_slave("read_holding_registers", slave, broadcast=False)
        req = P.read_request(P.READ_HOLDING_REGISTERS, address, count)
        return self._call(s, req, lambda p: P.parse_registers(p, count), 5 + 2 * count)

    def read_input_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 04."""
        s = P.check_slave("read_input_registers", slave, broadcast=False)
        req = P.read_request(P.READ_INPUT_REGISTERS, address, count)
        return self._call(s, req, lambda p: P.parse_registers(p, count), 5 + 2 * count)

    def write_coil(self, slave: int, address: int, value: bool) -> None:
        """FC 05 (slave 0 broadcasts)."""
        s = P.check_slave("write_coil", slave, broadcast=True)
        req = P.write_coil_request(address, value)
        self._write(s, req, lambda p: P.parse_echo(p, req), 8)

    def write_register(self, slave: int, address: int, value: int) -> None:
        """FC 06 (slave 0 broadcasts)."""
        s = P.check_slave("write_register", slave, broadcast=True)
        req = P.write_register_request(address, value)
        self._write(s, req, lambda p: P.parse_echo(p, req), 8)

    def write_coils(self, slave: int, address: int, values: Iterable[bool]) -> None:
        """FC 15 (slave 0 broadcasts)."""
        s = P.check_slave("write_coils", slave, broadcast=True)
        req = P.write_coils_request(address, values)
        self._write(s, req, lambda p: P.parse_echo(p, req, 5), 8)

    def write_registers(self, slave: int, address: int, values: Iterable[int]) -> None:
        """FC 16 (slave 0 broadcasts)."""
        s = P.check_slave("write_registers", slave, broadcast=True)
        req = P.write_registers_request(address, values)
        self._write(s, req, lambda p: P.parse_echo(p, req, 5), 8)

    def mask_write_register(self, slave: int, address: int, and_mask: int, or_mask: int) -> None:
        """FC 22: register = (register AND and_mask) OR (or_mask AND NOT and_mask)."""
        s = P.check_slave("mask_write_register", slave, broadcast=True)
        req = P.mask_write_request(address, and_mask, or_mask)
        self._write(s, req, lambda p: P.parse_echo(p, req), 10)

    def read_write_registers(
        self,
        slave: int,
        read_address: int,
        read_count: int,
        write_address: int,
        values: Iterable[int],
    ) -> list[int]:
        """FC 23: write ``values`` at ``write_address``, then read ``read_count`` registers."""
        s = P.check_slave("read_write_registers", slave, broadcast=False)
        req = P.read_write_request(read_address, read_count, write_address, values)
        return self._call(s, req, lambda p: P.parse_registers(p, read_count), 5 + 2 * read_count)

    # ----------------------------------------------------------- serial-line functions

    def read_exception_status(self, slave: int) -> int:
        """FC 07: the slave's eight exception status bits."""
        s = P.check_slave("read_exception_status", slave, broadcast=False)
        return self._call(s, bytes((P.READ_EXCEPTION_STATUS,)), P.parse_exception_status)

    def diagnostics(self, slave: int, sub_function: int, data: int = 0) -> int:
        """FC 08: the data word of the answer.  Sub-function 0x04 (force listen only
        mode) is never answered: it returns 0 once sent."""
        s = P.check_slave("diagnostics", slave, broadcast=False)
        req = P.diagnostics_request(sub_function, data)
        if sub_function == P.DIAG_FORCE_LISTEN_ONLY:
            self._transact(s, req, None)
            return 0
        return self._call(s, req, lambda p: P.parse_diagnostics(p, sub_function), 8)

    def get_comm_event_counter(self, slave: int) -> tuple[int, int]:
        """FC 11: (status, event count); status 0xFFFF means busy."""
        s = P.check_slave("get_comm_event_counter", slave, broadcast=False)
        return self._call(s, bytes((P.GET_COMM_EVENT_COUNTER,)), P.parse_event_counter)

    def get_comm_event_log(self, slave: int) -> P.CommEventLog:
        """FC 12: status, event count, message count and up to 64 events (newest first)."""
        s = P.check_slave("get_comm_event_log", slave, broadcast=False)
        return self._call(s, bytes((P.GET_COMM_EVENT_LOG,)), P.parse_event_log)

    def report_server_id(self, slave: int) -> bytes:
        """FC 17: the data after the byte count: server ID, run indicator (0xFF on,
        0x00 off), additional data, as the device sends them."""
        s = P.check_slave("report_server_id", slave, broadcast=False)
        return self._call(s, bytes((P.REPORT_SERVER_ID,)), P.parse_server_id)

    def read_fifo_queue(self, slave: int, address: int) -> list[int]:
        """FC 24: the FIFO queue at ``address`` (up to 31 registers)."""
        s = P.check_slave("read_fifo_queue", slave, broadcast=False)
        return self._call(s, P.fifo_request(address), P.parse_fifo)

    def read_file_record(
        self, slave: int, items: Sequence[tuple[int, int, int]]
    ) -> list[list[int]]:
        """FC 20: ``[(file, record, length), ...]`` -> the records' registers."""
        s = P.check_slave("read_file_record", slave, broadcast=False)
        req = P.read_file_request(items)
        got = list(items)
        return self._call(s, req, lambda p: P.parse_read_file(p, got))

    def write_file_record(
        self, slave: int, items: Sequence[tuple[int, int, Sequence[int]]]
    ) -> None:
        """FC 21: ``[(file, record, values), ...]`` (slave 0 broadcasts)."""
        s = P.check_slave("write_file_record", slave, broadcast=True)
        req = P.write_file_request(items)
        self._write(s, req, lambda p: P.parse_echo(p, req), 3 + len(req))

    def read_device_identification(
        self, slave: int, read_code: int = 1, object_id: int = 0
    ) -> dict[int, bytes]:
        """FC 43/14: ``{object_id: value}``; read codes 1-3 stream and follow More Follows
        / Next Object until complete, read code 4 reads one object."""
        where = "read_device_identification"
        s = P.check_slave(where, slave, broadcast=False)
        P.device_id_request(read_code, object_id)  # argument checks
        out: dict[int, bytes] = {}
        asked: set[int] = set()
        oid = object_id
        with self._lock:
            while True:
                asked.add(oid)
                page = self._call(
                    s,
                    P.device_id_request(read_code, oid),
                    lambda p: P.parse_device_id(p, read_code),
                )
                out.update(page.objects)
                if read_code == 4 or not page.more_follows:
                    return out
                if page.next_object in asked:
                    self._counters["frame_errors"] += 1
                    raise FrameError(
                        f"{where}: slave {s}: Next Object {page.next_object} was already read",
                        s,
                        P.ENCAPSULATED_INTERFACE,
                    )
                oid = page.next_object

    def execute(
        self,
        slave: int,
        function: int,
        data: bytes = b"",
        *,
        request_rule: LengthRule | None = None,
        response_rule: LengthRule | None = None,
    ) -> bytes:
        """Any function code: send ``function`` + ``data``, return the response data
        (after the function code).  ``response_rule`` frames a vendor response by its
        length (no wait for silence).  Slave 0 broadcasts for any function (the master
        cannot tell a vendor write from a read) and returns b""."""
        where = f"function {function}"
        s = P.check_slave(where, slave, broadcast=True)
        if isinstance(function, bool) or not isinstance(function, int) or not 1 <= function <= 127:
            raise ValueError(f"execute: function must be 1..127, not {function!r}")
        if not isinstance(data, bytes | bytearray | memoryview):
            raise ValueError(f"execute: data must be bytes, not {type(data).__name__}")
        request = bytes((function,)) + bytes(data)
        if len(request) > P.MAX_PDU:
            raise ValueError(f"execute: a {len(request)}-byte PDU exceeds {P.MAX_PDU} bytes")
        if request_rule is not None or response_rule is not None:
            self.add_rule(function, request_rule, response_rule)
        if s == 0:
            self._transact(s, request, None)
            return b""
        return self._call(s, request, lambda p: p[1:])


__all__ = ["Master"]
