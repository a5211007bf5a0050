"""The Modbus master (client) over a serial line, RTU or ASCII.

::

    with pyrtu.Master("/dev/ttyUSB0", 19200, parity="E", timeout=0.5) as bus:
        speed, current = bus.read_holding_registers(1, 2, 2)
        bus.write_register(3, 683, 0x1000)

One transaction at a time per bus (a lock makes the object thread-safe).  The
transaction itself is the sans-I/O `pyrtu._client.ClientProtocol`: it keeps the
inter-frame silence (t3.5 after the end of the last frame on the wire, measured
from when transmission actually ended and from the last byte received; ``t35=0``
turns it off), drops stale input, checks the echo (``echo=True``), recognises the
answer by its predicted length as soon as its last byte is in, and ends with the
decoded answer or a typed error.  This module is the thin blocking driver: it
writes, waits for input (sleeping the character times of the bytes the answer
still needs rather than waking per byte) and feeds the protocol.

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

import math
import threading
from collections.abc import Iterable, Sequence
from typing import Any

from . import _backend
from . import _requests as R
from . import pdu as P
from ._client import ClientProtocol
from ._master_io import run_sync
from ._requests import Call
from ._transports import transport_for
from .errors import PortError
from .line import LineConfig
from .port import Port, open_line_port
from .rules import LengthRule, RuleTable, check_rules

_LINE_DEFAULTS: dict[str, Any] = dict(
    baudrate=19200,
    parity="E",
    stopbits=1,
    bytesize=8,
    mode="rtu",
    timing="modbus",
    t15=None,
    t35=None,
    rules=None,
    max_adu=256,
    strict=False,
)


def check_seconds(name: str, value: object, positive: bool = False) -> float:
    """A finite duration in seconds; ValueError naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number of seconds, not {value!r}")
    if value < 0 or (positive and value == 0):
        raise ValueError(
            f"{name} must be {'positive' if positive else 'non-negative'}, not {value!r}"
        )
    return float(value)


def check_retries(retries: object) -> int:
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise ValueError(f"retries must be a non-negative integer, not {retries!r}")
    return retries


def make_line(line: LineConfig | None, **kwargs: Any) -> LineConfig:
    """The LineConfig of a master or slave: ``line``, or one from the line keywords
    (TypeError when both are given)."""
    if line is None:
        kwargs["rules"] = kwargs["rules"] or {}
        return LineConfig(**kwargs)
    if not isinstance(line, LineConfig):
        raise TypeError(f"line must be a LineConfig, not {type(line).__name__}")
    given = [k for k, v in kwargs.items() if v != _LINE_DEFAULTS[k]]
    if given:
        raise TypeError(f"give line= or the line keywords ({', '.join(given)}), not both")
    return line


def adopt_port_format(line: LineConfig, p: Port) -> LineConfig:
    """A pyserial object passed in keeps its own format: the line follows it."""
    fmt = dict(baudrate=p.baudrate, parity=p.parity, stopbits=p.stopbits, bytesize=p.bytesize)
    if all(getattr(line, k) == v for k, v in fmt.items()):
        return line
    return line.replace(**fmt)


class MasterBase:
    """What the sync and asyncio masters share: options, the protocol, counters."""

    port: Port
    _proto: ClientProtocol

    def _setup(
        self,
        port: Any,
        line: LineConfig,
        timeout: float,
        retries: int,
        echo: bool,
        rs485: Any,
        broadcast_delay: float,
        backend: str | None,
        exclusive: bool,
    ) -> None:
        timeout = check_seconds("timeout", timeout, positive=True)
        retries = check_retries(retries)
        broadcast_delay = check_seconds("broadcast_delay", broadcast_delay)
        be = _backend.backend(backend)
        # every option is checked before the port is opened
        self.port = open_line_port(port, line, rs485, exclusive)
        self._proto = ClientProtocol(
            adopt_port_format(line, self.port),
            timeout=timeout,
            retries=retries,
            echo=bool(echo),
            broadcast_delay=broadcast_delay,
            backend=be,
        )

    @property
    def line(self) -> LineConfig:
        """The line's configuration."""
        return self._proto.line

    @property
    def mode(self) -> str:
        return self._proto.line.mode

    @property
    def t35(self) -> float:
        """The inter-frame silence the master keeps before a request (seconds; 0: none)."""
        return self._proto.gap

    @property
    def timeout(self) -> float:
        return self._proto.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._proto.timeout = check_seconds("timeout", value, positive=True)

    @property
    def retries(self) -> int:
        return self._proto.retries

    @retries.setter
    def retries(self, value: int) -> None:
        self._proto.retries = check_retries(value)

    @property
    def echo(self) -> bool:
        return self._proto.echo

    @property
    def broadcast_delay(self) -> float:
        return self._proto.broadcast_delay

    @property
    def last_answer_time(self) -> float | None:
        """When the last byte of the latest answer arrived (monotonic seconds), or
        None before the first answer."""
        return self._proto.answer_end

    def _set_rules(self, function: int, request_rule: Any, response_rule: Any) -> None:
        new = check_rules({function: (request_rule, response_rule)})
        rules = dict(self._proto.line.rules)
        if rules.get(function) != new[function]:
            rules.update(new)
            self._proto.set_line(self._proto.line.replace(rules=rules))

    def __repr__(self) -> str:
        return (
            f"<pyrtu.{type(self).__name__} {self.port.name} {self.mode} {self.port.baudrate} baud>"
        )


class Master(MasterBase):
    """A Modbus master on one serial line (see the module docstring).

    ``line``: a `LineConfig` instead of the line keywords (baudrate, parity,
    stopbits, bytesize, mode, timing, t15, t35, rules, max_adu, strict);
    ``exclusive``: lock the port against other processes (passed to open_port).
    """

    def __new__(cls, port: Any = None, *args: Any, **kwargs: Any) -> Master:
        # tcp://, rtu+tcp://: the transport's subclass (pyrtu._transports)
        sub = transport_for("sync", port) if cls is Master else None
        return super().__new__(sub or cls)

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
        line: LineConfig | None = None,
        exclusive: bool = True,
    ) -> None:
        cfg = make_line(
            line,
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            bytesize=bytesize,
            mode=mode,
            timing=timing,
            t15=t15,
            t35=t35,
            rules=rules,
            max_adu=max_adu,
            strict=strict,
        )
        self._lock = threading.RLock()
        self._setup(port, cfg, timeout, retries, echo, rs485, broadcast_delay, backend, exclusive)

    # ----------------------------------------------------------------- plumbing

    def _run(self, call: Call) -> Any:
        with self._lock:
            if self.port.closed:
                raise PortError(self.port.name, "the master is closed")
            return run_sync(self.port, self._proto, call)

    def add_rule(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        """Register length rules for a (vendor) function code in the framer."""
        with self._lock:
            self._set_rules(function, request_rule, response_rule)

    @property
    def counters(self) -> dict[str, int]:
        """requests, responses, broadcasts, exceptions, timeouts, crc_errors, frame_errors,
        echo_mismatches, retries, discarded bytes (total and per reason)."""
        with self._lock:
            return dict(self._proto.counters)

    def close(self) -> None:
        """Close the port (a pyserial object passed in is left open)."""
        with self._lock:
            self.port.close()

    def __enter__(self) -> Master:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- any request

    def request(self, slave: int, pdu: bytes) -> bytes:
        """Send a request PDU (function code + data, e.g. from `pyrtu.pdu`) and return
        the response PDU (function code + data).  An exception response raises
        `ExceptionResponseError`; slave 0 broadcasts and returns b""."""
        return self._run(R.raw_request(slave, pdu)) or b""

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
        call = R.execute(slave, function, data, request_rule, response_rule)
        if request_rule is not None or response_rule is not None:
            self.add_rule(function, request_rule, response_rule)
        return self._run(call) or b""

    # ---------------------------------------------------------------- bit/word access

    def read_coils(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 01: ``count`` coils from ``address``."""
        return self._run(R.read_coils(slave, address, count))  # type: ignore[no-any-return]

    def read_discrete_inputs(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 02."""
        return self._run(R.read_discrete_inputs(slave, address, count))  # type: ignore[no-any-return]

    def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 03."""
        return self._run(R.read_holding_registers(slave, address, count))  # type: ignore[no-any-return]

    def read_input_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 04."""
        return self._run(R.read_input_registers(slave, address, count))  # type: ignore[no-any-return]

    def write_coil(self, slave: int, address: int, value: bool) -> None:
        """FC 05 (slave 0 broadcasts)."""
        self._run(R.write_coil(slave, address, value))

    def write_register(self, slave: int, address: int, value: int) -> None:
        """FC 06 (slave 0 broadcasts)."""
        self._run(R.write_register(slave, address, value))

    def write_coils(self, slave: int, address: int, values: Iterable[bool]) -> None:
        """FC 15 (slave 0 broadcasts)."""
        self._run(R.write_coils(slave, address, values))

    def write_registers(self, slave: int, address: int, values: Iterable[int]) -> None:
        """FC 16 (slave 0 broadcasts)."""
        self._run(R.write_registers(slave, address, values))

    def mask_write_register(self, slave: int, address: int, and_mask: int, or_mask: int) -> None:
        """FC 22: register = (register AND and_mask) OR (or_mask AND NOT and_mask)."""
        self._run(R.mask_write_register(slave, address, and_mask, or_mask))

    def read_write_registers(
        self,
        slave: int,
        read_address: int,
        read_count: int,
        write_address: int,
        values: Iterable[int],
    ) -> list[int]:
        """FC 23: write ``values`` at ``write_address``, then read ``read_count`` registers."""
        call = R.read_write_registers(slave, read_address, read_count, write_address, values)
        return self._run(call)  # type: ignore[no-any-return]

    # ----------------------------------------------------------- serial-line functions

    def read_exception_status(self, slave: int) -> int:
        """FC 07: the slave's eight exception status bits."""
        return self._run(R.read_exception_status(slave))  # type: ignore[no-any-return]

    def diagnostics(self, slave: int, sub_function: int, data: int = 0) -> int:
        """FC 08: the data word of the answer.  Sub-function 0x04 (force listen only
        mode) is never answered: it returns 0 once sent."""
        return self._run(R.diagnostics(slave, sub_function, data)) or 0

    def get_comm_event_counter(self, slave: int) -> tuple[int, int]:
        """FC 11: (status, event count); status 0xFFFF means busy."""
        return self._run(R.get_comm_event_counter(slave))  # type: ignore[no-any-return]

    def get_comm_event_log(self, slave: int) -> P.CommEventLog:
        """FC 12: status, event count, message count and up to 64 events (newest first)."""
        return self._run(R.get_comm_event_log(slave))  # type: ignore[no-any-return]

    def report_server_id(self, slave: int) -> bytes:
        """FC 17: the data after the byte count: server ID, run indicator (0xFF on,
        0x00 off), additional data, as the device sends them."""
        return self._run(R.report_server_id(slave))  # type: ignore[no-any-return]

    def read_fifo_queue(self, slave: int, address: int) -> list[int]:
        """FC 24: the FIFO queue at ``address`` (up to 31 registers)."""
        return self._run(R.read_fifo_queue(slave, address))  # type: ignore[no-any-return]

    def read_file_record(
        self, slave: int, items: Sequence[tuple[int, int, int]]
    ) -> list[list[int]]:
        """FC 20: ``[(file, record, length), ...]`` -> the records' registers."""
        return self._run(R.read_file_record(slave, items))  # type: ignore[no-any-return]

    def write_file_record(
        self, slave: int, items: Sequence[tuple[int, int, Sequence[int]]]
    ) -> None:
        """FC 21: ``[(file, record, values), ...]`` (slave 0 broadcasts)."""
        self._run(R.write_file_record(slave, items))

    def read_device_identification(
        self, slave: int, read_code: int = 1, object_id: int = 0
    ) -> dict[int, bytes]:
        """FC 43/14: ``{object_id: value}``; read codes 1-3 stream and follow More Follows
        / Next Object until complete, read code 4 reads one object."""
        s = R.device_id_check(slave, read_code, object_id)
        out: dict[int, bytes] = {}
        asked: set[int] = set()
        oid: int | None = object_id
        with self._lock:
            while oid is not None:
                asked.add(oid)
                page = self._run(R.device_id_page(s, read_code, oid))
                try:
                    oid = R.device_id_next(s, read_code, page, out, asked)
                except Exception:
                    self._proto.counters["frame_errors"] += 1
                    raise
            return out


__all__ = ["Master"]
