"""The Modbus master (client): one class on any transport.

The port string picks the master's link (`pyrtu.drivers.links`): a serial line, RTU or
ASCII (a device path, a pyserial object or URL), ``rtu+tcp://host:port`` (RTU
frames over a socket, ``t35`` 0 unless given), ``tcp://host:port`` (Modbus TCP) or
``mbaps://host[:802]`` (Modbus TCP in TLS, with ``tls=``; both
`pyrtu.tcp.link`).  The request methods are one table (`pyrtu.pdu.requests`)
shared with `pyrtu.drivers.aio.AsyncMaster` and the poller; ``transact`` runs one with
the answer's end time.

::

    with pyrtu.Master("/dev/ttyUSB0", 19200, parity="E", timeout=0.5) as bus:
        speed, current = bus.read_holding_registers(1, 2, 2)
        bus.write_register(3, 683, 0x1000)

One transaction at a time per bus (a lock makes the object thread-safe).  The
transaction itself is the sans-I/O `pyrtu.protocol.ClientProtocol`: it keeps the
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

A port that fails (a USB adapter pulled out: EIO) is closed and reopened at a later
request, the same path with the same line and options, on the back-off of
`pyrtu.drivers.reconnect` (`SerialLink.ready`, `pyrtu.drivers.links.LinkRevival`); a
request while it is away raises `PortError` at once, saying when the next attempt is.
An ``rtu+tcp://`` connection the device server closed or reset is made again the same
way (`RtuOverTcpLink`), as a ``tcp://`` link reconnects.  A pyserial object handed in
is the caller's: not reopened.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

from pyrtu import pdu as pdus
from pyrtu.core import _backend
from pyrtu.core._forward import Forward, Settable
from pyrtu.core.line import LineConfig, adopt_port_format, line_from
from pyrtu.core.rules import LengthRule, RuleTable, check_rules
from pyrtu.drivers import xfer_runners
from pyrtu.drivers.links import (
    Link,
    LinkRevival,
    check_in_flight,
    check_retries,
    check_seconds,
    check_tls,
    transport_of,
)
from pyrtu.drivers.port import Port, open_line_port
from pyrtu.drivers.sync_io import run_sync
from pyrtu.pdu import requests as request_table
from pyrtu.pdu.errors import PortError
from pyrtu.pdu.requests import Call, Request, Rules, Steps
from pyrtu.protocol.client import ClientProtocol

if TYPE_CHECKING:
    from pyrtu.tcp.link import TcpLink

_monotonic = time.monotonic


def _of_proto(name: str, settable: bool = False) -> Any:
    """A link property that is the client protocol's attribute ``name``."""

    def get(link: SerialLink) -> Any:
        return getattr(link.proto, name)

    def put(link: SerialLink, value: Any) -> None:
        setattr(link.proto, name, value)

    return property(get, put if settable else None)


class SerialLink:
    """A serial line as a master's link (`pyrtu.drivers.links`): the port and the client
    protocol.  Every option is checked before the port is opened."""

    @classmethod
    def open(
        cls, port: Any, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> SerialLink:
        """The link of `pyrtu.drivers.links.TRANSPORTS` (``tls`` is None here)."""
        return cls(port, line, **{k: v for k, v in options.items() if k != "tls"})

    def __init__(
        self,
        port: Any,
        line: LineConfig,
        *,
        timeout: float,
        retries: int,
        echo: bool,
        rs485: Any,
        broadcast_delay: float,
        backend: str | None,
        exclusive: bool,
        opener: Callable[[LineConfig], Port] | None = None,
    ) -> None:
        be = self._backend = _backend.backend(backend)
        #: opens the port with a line's format, again after it failed: the same path
        #: (or ``rtu+tcp://`` URL: `RtuOverTcpLink`) and options (None: a pyserial object
        #: the user opened, not ours to open again)
        self._opener = opener
        if opener is None and isinstance(port, str):
            path = port
            self._opener = lambda cfg: open_line_port(path, cfg, rs485, exclusive)
        opened = self._opener
        self.port: Port = (
            open_line_port(port, line, rs485, exclusive) if opened is None else opened(line)
        )
        try:
            self.proto = ClientProtocol(
                adopt_port_format(line, self.port),
                timeout=timeout,
                retries=retries,
                echo=bool(echo),
                broadcast_delay=broadcast_delay,
                backend=be,
            )
        except BaseException:
            self.port.close()  # (an option refused: a port opened for it goes)
            raise
        #: a repeated request's xfer: its transaction in one call (see pyrtu.drivers.sync_io)
        self.xfer_runner = xfer_runners.xfer_runner(be) if self.port.fd is not None else None
        #: whether the port failed (closed, reopened at a later request on the back-off)
        self.broken = False
        self._revive = LinkRevival(self.port.name, verb="reopen", down="not open")

    #: whether reopening the port waits on the network (an asyncio master does it
    #: on a worker thread, not on its event loop)
    reopen_blocks = False

    line = _of_proto("line")
    t35 = _of_proto("gap")
    timeout = _of_proto("timeout", settable=True)
    retries = _of_proto("retries", settable=True)
    echo = _of_proto("echo")
    broadcast_delay = _of_proto("broadcast_delay")
    last_answer_time = _of_proto("answer_end")

    @property
    def mode(self) -> str:
        return self.proto.line.mode

    @property
    def counters(self) -> dict[str, int]:
        return dict(self.proto.counters)

    address = staticmethod(request_table.serial_address)

    def count_bad(self) -> None:
        self.proto.counters["frame_errors"] += 1

    def set_rules(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        new = check_rules({function: (request_rule, response_rule)})
        rules = dict(self.proto.line.rules)
        if rules.get(function) != new[function]:
            rules.update(new)
            self.proto.set_line(self.proto.line.replace(rules=rules))

    def end_of(self, call: Call) -> float:
        """When the answer to ``call`` ended (now for one not awaited)."""
        end = self.proto.answer_end
        return _monotonic() if call.decode is None or end is None else end

    def transact(self, call: Call) -> tuple[Any, float]:
        """One transaction (blocking)."""
        self.ready()
        try:
            return run_sync(self.port, self.proto, call, self.xfer_runner), self.end_of(call)
        except PortError:
            self.failed()
            raise

    def ready(self) -> None:
        """Before a transaction: `PortError` once the master is closed; a port that
        failed is reopened if its next attempt is due (`LinkRevival`), else
        `PortError` at once, saying when it is."""
        if self._revive.closed:
            raise PortError(self.port.name, "the master is closed")
        if self.broken:
            self._revive.attempt(self._reopen)

    def reopen_due(self) -> bool:
        """Whether `ready` would try to reopen the port now (it failed, and its next
        attempt is due), not return or raise at once."""
        revive = self._revive
        return self.broken and not revive.closed and revive.reconnect.due(_monotonic())

    def failed(self) -> None:
        """A transaction failed with `PortError` (the device gone: EIO...): the port is
        closed, to be reopened at a later request (not a pyserial object the user
        opened: its calls go on failing, or working if it comes back by itself)."""
        if self._opener is not None:
            self.broken = True
            self.port.close()

    def _reopen(self) -> None:
        assert self._opener is not None
        self.port = self._opener(self.proto.line)
        self.broken = False
        if self.port.fd is not None and self.xfer_runner is None:
            self.xfer_runner = xfer_runners.xfer_runner(self._backend)

    def close(self) -> None:
        self._revive.closed = True
        self.port.close()

    @property
    def url(self) -> str:
        raise AttributeError(f"{self.port.name}: a serial master has no url (see port, line)")

    def describe(self) -> str:
        return f"{self.port.name} {self.mode} {self.port.baudrate} baud"


class RtuOverTcpLink(SerialLink):
    """``rtu+tcp://host:port``: the serial link's RTU frames over a TCP socket.  A
    connection that fails (the device server closed or reset it, or is unreachable)
    is closed and made again at a later request, to the same URL with the same line
    and options, on the back-off (`SerialLink.ready`, `LinkRevival`), as a ``tcp://``
    link reconnects."""

    reopen_blocks = True  # a connect: up to pyserial's socket:// timeout

    @classmethod
    def open(
        cls, port: Any, line: LineConfig, options: dict[str, Any], max_in_flight: int
    ) -> SerialLink:
        url: str = port
        rs485, exclusive = options["rs485"], options["exclusive"]

        def connect(cfg: LineConfig) -> Port:
            from pyrtu.tcp import rtu_over_tcp  # (loads the TCP module only when used)

            sock = rtu_over_tcp(url)
            try:
                opened = open_line_port(sock, cfg, rs485, exclusive)
            except BaseException:
                sock.close()  # (an option refused: the connection made for it goes)
                raise
            opened.owned = True  # made here, not handed in: the master's close closes it
            return opened

        options = {k: v for k, v in options.items() if k != "tls"}
        link = cls(url, line, opener=connect, **options)
        link._revive = LinkRevival(url)  # as a tcp:// link's: "reconnect", "not connected"
        return link

    @staticmethod
    def check_port(port: str) -> None:
        """ValueError naming ``port`` unless it is ``rtu+tcp://HOST[:PORT]``."""
        from pyrtu.tcp.client import parse_rtu_tcp_url

        parse_rtu_tcp_url(port)


class MasterBase:
    """The one master class's shared part (`Master`, and `pyrtu.drivers.aio.AsyncMaster`
    for asyncio): the keywords, the link the port string picks, the properties.

    ``line``: a `LineConfig` instead of the line keywords (baudrate, parity,
    stopbits, bytesize, mode, timing, t15, t35, rules, max_adu, strict), checked on
    every transport; ``exclusive``: lock the port against other processes (passed
    to open_port); ``max_in_flight``: requests on the wire at once (more than 1
    only for an `AsyncMaster` on ``tcp://`` or ``mbaps://``); ``tls``: the
    `ssl.SSLContext` of an ``mbaps://`` port (Modbus/TCP Security, port 802 by default:
    ``pyrtu.security.tls.client_context(cert, key, ca)``; required there, refused
    elsewhere).
    """

    _link: Link
    #: whether this class keeps several requests on a tcp:// connection at once
    _PIPELINES = False

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
        max_in_flight: int = 1,
        tls: Any = None,
    ) -> None:
        transport = transport_of(port)
        cfg = line_from(
            line, baudrate=baudrate, parity=parity, stopbits=stopbits, bytesize=bytesize,
            mode=mode, timing=timing, t15=t15, t35=t35, rules=rules, max_adu=max_adu,
            strict=strict,
        )  # fmt: skip
        if transport.t35 is not None and cfg.t35 is None:
            cfg = cfg.replace(t35=transport.t35)  # a socket has no wire timing
        options = dict(
            timeout=check_seconds("timeout", timeout, positive=True),
            retries=check_retries(retries),
            echo=echo,
            rs485=rs485,
            broadcast_delay=check_seconds("broadcast_delay", broadcast_delay),
            backend=backend,
            exclusive=exclusive,
            tls=check_tls(transport, tls),
        )
        in_flight = check_in_flight(max_in_flight, self._PIPELINES and transport.pipelines)
        _backend.backend(backend)  # (checked before a port is opened or connected)
        link_class = transport.link_class(self._PIPELINES)
        self._link = self._open(link_class.open(port, cfg, options, in_flight))

    def _open(self, link: Any) -> Link:
        """Take the link the port string's transport opened (`pyrtu.drivers.links`)."""
        raise NotImplementedError

    # what the link answers for, read by name (declared here only, see `pyrtu.drivers.links.Link`)
    line = Forward[LineConfig](
        "_link", doc="The line's configuration (a TCP master has none: AttributeError)."
    )
    port = Forward[Port]("_link", doc="The serial port (a TCP master has none: AttributeError).")
    url = Forward[str](
        "_link", doc="The ``tcp://`` URL of a TCP master (a serial master has none)."
    )
    mode = Forward[str]("_link", doc='"rtu", "ascii" or "tcp".')
    t35 = Forward[float](
        "_link",
        doc="The inter-frame silence the master keeps before a request (seconds; 0: none).",
    )
    timeout = Settable[float]("_link", lambda value: check_seconds("timeout", value, True))
    retries = Settable[int]("_link", check_retries)
    echo = Forward[bool]("_link")
    broadcast_delay = Forward[float]("_link")
    last_answer_time = Forward[float | None](
        "_link",
        doc="When the last byte of the latest answer arrived (monotonic seconds), or None"
        " before the first answer.",
    )

    @property
    def counters(self) -> dict[str, int]:
        """requests, responses, broadcasts, exceptions, timeouts, crc_errors, frame_errors,
        echo_mismatches, retries, discarded bytes (total and per reason)."""
        return self._link.counters

    def _steps(self, req: Request[Any] | str, slave: Any, args: Any, kwargs: Any) -> Steps:
        request = request_table.REQUESTS[req] if isinstance(req, str) else req
        link = self._link
        return Steps(request, slave, args, kwargs, link.address, link.count_bad)

    def __repr__(self) -> str:
        return f"<pyrtu.{type(self).__name__} {self._link.describe()}>"


class Master(MasterBase):
    """A Modbus master on one serial line, or on ``tcp://`` / ``rtu+tcp://`` (see the
    module docstring and `MasterBase` for the keywords)."""

    def _open(self, link: Any) -> Link:
        self._lock = threading.RLock()
        self._conn: TcpLink | SerialLink = link
        opened: Link = link
        return opened

    # ----------------------------------------------------------------- plumbing

    def transact(
        self, req: Request[Any] | str, slave: Any, *args: Any, **kwargs: Any
    ) -> tuple[Any, float]:
        """Run the request ``req`` (a `pyrtu.pdu.requests.Request` or a method name) with
        the method's arguments: ``(value, end_time)``, ``end_time`` being when the
        answer's last byte came (monotonic seconds)."""
        request = request_table.REQUESTS[req] if isinstance(req, str) else req
        with self._lock:
            if request.build is not None:  # one transaction: no plan to step through
                call = request_table.call_of(request, slave, args, kwargs, self._link.address)
                value, end = self._conn.transact(call)
                return (value if request.post is None else request.post(value)), end
            steps = self._steps(request, slave, args, kwargs)
            step = steps.next()
            while step is not None:
                step = steps.next(*self._step(step))
            return steps.value, steps.end  # type: ignore[return-value]

    def _step(self, step: Call | Rules) -> tuple[Any, float | None]:
        if isinstance(step, Rules):
            self._link.set_rules(*step)
            return None, None
        return self._conn.transact(step)

    def _call(self, name: str, slave: Any, *args: Any, **kwargs: Any) -> Any:
        return self.transact(name, slave, *args, **kwargs)[0]

    def add_rule(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        """Register length rules for a (vendor) function code in the framer (nothing
        on TCP: the MBAP length ends every answer)."""
        with self._lock:
            self._link.set_rules(function, request_rule, response_rule)

    @property
    def counters(self) -> dict[str, int]:
        """requests, responses, broadcasts, exceptions, timeouts, crc_errors, frame_errors,
        echo_mismatches, retries, discarded bytes (total and per reason)."""
        with self._lock:
            return self._link.counters

    def close(self) -> None:
        """Close the port (a pyserial object passed in is left open); a closed master
        stays closed (its port is not reopened)."""
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Master:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- any request

    def request(self, slave: int, pdu: bytes) -> bytes:
        """Send a request PDU (function code + data, e.g. from `pyrtu.pdu`) and return
        the response PDU (function code + data).  An exception response raises
        `ExceptionResponseError`; slave 0 broadcasts and returns b""."""
        return self._call("request", slave, pdu)  # type: ignore[no-any-return]

    def exchange(self, slave: int, pdu: bytes) -> bytes:
        """As `request`, but an exception response is returned as its PDU (function
        code | 0x80, exception code) instead of raised (a gateway forwards it as it
        came).  Slave 0 broadcasts and returns b""."""
        return self._call("exchange", slave, pdu)  # type: ignore[no-any-return]

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
        rules = dict(request_rule=request_rule, response_rule=response_rule)
        return self._call("execute", slave, function, data, **rules)  # type: ignore[no-any-return]

    # ---------------------------------------------------------------- bit/word access

    def read_coils(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 01: ``count`` coils from ``address``."""
        return self._call("read_coils", slave, address, count)  # type: ignore[no-any-return]

    def read_discrete_inputs(self, slave: int, address: int, count: int) -> list[bool]:
        """FC 02."""
        return self._call("read_discrete_inputs", slave, address, count)  # type: ignore[no-any-return]

    def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 03."""
        return self._call("read_holding_registers", slave, address, count)  # type: ignore[no-any-return]

    def read_input_registers(self, slave: int, address: int, count: int) -> list[int]:
        """FC 04."""
        return self._call("read_input_registers", slave, address, count)  # type: ignore[no-any-return]

    def write_coil(self, slave: int, address: int, value: bool) -> None:
        """FC 05 (slave 0 broadcasts)."""
        self._call("write_coil", slave, address, value)

    def write_register(self, slave: int, address: int, value: int) -> None:
        """FC 06 (slave 0 broadcasts)."""
        self._call("write_register", slave, address, value)

    def write_coils(self, slave: int, address: int, values: Iterable[bool]) -> None:
        """FC 15 (slave 0 broadcasts)."""
        self._call("write_coils", slave, address, values)

    def write_registers(self, slave: int, address: int, values: Iterable[int]) -> None:
        """FC 16 (slave 0 broadcasts)."""
        self._call("write_registers", slave, address, values)

    def mask_write_register(self, slave: int, address: int, and_mask: int, or_mask: int) -> None:
        """FC 22: register = (register AND and_mask) OR (or_mask AND NOT and_mask)."""
        self._call("mask_write_register", slave, address, and_mask, or_mask)

    def read_write_registers(
        self,
        slave: int,
        read_address: int,
        read_count: int,
        write_address: int,
        values: Iterable[int],
    ) -> list[int]:
        """FC 23: write ``values`` at ``write_address``, then read ``read_count`` registers."""
        args = (read_address, read_count, write_address, values)
        return self._call("read_write_registers", slave, *args)  # type: ignore[no-any-return]

    # ----------------------------------------------------------- serial-line functions

    def read_exception_status(self, slave: int) -> int:
        """FC 07: the slave's eight exception status bits."""
        return self._call("read_exception_status", slave)  # type: ignore[no-any-return]

    def diagnostics(self, slave: int, sub_function: int, data: int = 0) -> int:
        """FC 08: the data word of the answer.  Sub-function 0x04 (force listen only
        mode) is never answered: it returns 0 once sent."""
        return self._call("diagnostics", slave, sub_function, data)  # type: ignore[no-any-return]

    def get_comm_event_counter(self, slave: int) -> tuple[int, int]:
        """FC 11: (status, event count); status 0xFFFF means busy."""
        return self._call("get_comm_event_counter", slave)  # type: ignore[no-any-return]

    def get_comm_event_log(self, slave: int) -> pdus.CommEventLog:
        """FC 12: status, event count, message count and up to 64 events (newest first)."""
        return self._call("get_comm_event_log", slave)  # type: ignore[no-any-return]

    def report_server_id(self, slave: int) -> bytes:
        """FC 17: the data after the byte count: server ID, run indicator (0xFF on,
        0x00 off), additional data, as the device sends them."""
        return self._call("report_server_id", slave)  # type: ignore[no-any-return]

    def read_fifo_queue(self, slave: int, address: int) -> list[int]:
        """FC 24: the FIFO queue at ``address`` (up to 31 registers)."""
        return self._call("read_fifo_queue", slave, address)  # type: ignore[no-any-return]

    def read_file_record(
        self, slave: int, items: Sequence[tuple[int, int, int]]
    ) -> list[list[int]]:
        """FC 20: ``[(file, record, length), ...]`` -> the records' registers."""
        return self._call("read_file_record", slave, items)  # type: ignore[no-any-return]

    def write_file_record(
        self, slave: int, items: Sequence[tuple[int, int, Sequence[int]]]
    ) -> None:
        """FC 21: ``[(file, record, values), ...]`` (slave 0 broadcasts)."""
        self._call("write_file_record", slave, items)

    def read_device_identification(
        self, slave: int, read_code: int = 1, object_id: int = 0
    ) -> dict[int, bytes]:
        """FC 43/14: ``{object_id: value}``; read codes 1-3 stream and follow More Follows
        / Next Object until complete, read code 4 reads one object (the pages are one
        transaction after another, none in between)."""
        args = (read_code, object_id)
        return self._call("read_device_identification", slave, *args)  # type: ignore[no-any-return]


__all__ = ["Master"]
