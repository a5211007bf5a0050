"""`Master` and `AsyncMaster` over Modbus TCP: ``Master("tcp://host:port")``.

The same methods, argument checks and decoders (`pyrtu._requests`), with the
transport of `pyrtu.tcp` in place of the serial line: MBAP frames, transaction ids,
no CRC and no wire timing (the length field ends each answer).  ``timeout`` and
``retries`` keep their meaning (a retry after `NoResponseError` only); the serial
keywords are accepted and ignored, so code can switch transports by the port
string.  The asyncio master keeps up to ``max_in_flight`` requests on the
connection at once (``asyncio.gather`` of several awaits), for servers that answer
pipelined requests (libmodbus does; pymodbus 3.16's server does not: keep 1).

What `pyrtu.Master` says of its serial line, a TCP master answers for TCP:
``mode`` is ``"tcp"``, ``t35``, ``broadcast_delay`` are 0.0 (no wire timing: the
master keeps no silence and a broadcast returns at once), ``echo`` is False,
``last_answer_time`` is when the latest answer was read (what the poller stamps
values with), ``url`` is the URL given.  ``line`` and ``port`` (the `LineConfig` and
the pyserial port of a serial master) do not exist: reading them raises
AttributeError (``line``'s message names the URL and says why), so
``hasattr(m, "line")`` is False and ``getattr(m, "line", None)`` is None: code
tells a serial master from a TCP one that way.

Unit ids (Messaging on TCP/IP Implementation Guide 4.4.1.2): every method takes
0..255 where a serial master takes 0..247.  0xFF (libmodbus's default, the guide's
recommendation for a TCP device) and 248..254 address what is behind the
connection; 0 in a method that reads (where a serial master refuses the broadcast)
addresses the TCP device itself and its answer is awaited ("the value 0 is also
accepted to communicate directly to a MODBUS/TCP device"); 0 in a write,
``request`` or ``execute`` stays the broadcast (no answer awaited), as through a
gateway.  ``add_rule`` is accepted and does
nothing.  (Not None: a `LineConfig | None` would widen the type every caller of
``Master.line`` relies on.)
"""

from __future__ import annotations

import asyncio
import functools
import threading
from collections.abc import Callable
from contextvars import ContextVar
from typing import Any

from ._requests import Call
from ._transports import TRANSPORTS
from .aio import AsyncMaster
from .errors import NoResponseError
from .master import Master, check_retries, check_seconds
from .tcp import RTU_TCP_SCHEME, AsyncTcpClient, TcpClient, parse_tcp_url, rtu_over_tcp

MODE = "tcp"
NO_LINE = (
    "{url}: a Modbus TCP master has no serial line (line and port are a serial "
    "master's; see url, timeout, retries)"
)


#: the unit id a method was called with, where the argument checks shared with the
#: serial master (0..247) were given a stand-in address: set for the duration of the
#: call (a context variable: each asyncio task has its own)
_UNIT: ContextVar[int | None] = ContextVar("pyrtu_tcp_unit", default=None)
_STAND_IN = 1

#: the methods whose unit 0 is a broadcast (a serial master allows it); in the others
#: unit 0 is the TCP device itself and is answered
_BROADCASTING = frozenset(
    {"request", "execute", "write_coil", "write_register", "write_coils", "write_registers",
     "mask_write_register", "write_file_record"}
)  # fmt: skip
_ADDRESSED = frozenset(
    {"read_coils", "read_discrete_inputs", "read_holding_registers", "read_input_registers",
     "read_write_registers", "read_exception_status", "diagnostics", "get_comm_event_counter",
     "get_comm_event_log", "report_server_id", "read_fifo_queue", "read_file_record",
     "read_device_identification"}
)  # fmt: skip


def _tcp_unit(slave: object, broadcasting: bool) -> int | None:
    """The unit id to send when ``slave`` is one only TCP allows, else None."""
    if type(slave) is int and (248 <= slave <= 255 or (slave == 0 and not broadcasting)):
        return slave
    return None


def _sync_method(base: Callable[..., Any], broadcasting: bool) -> Callable[..., Any]:
    @functools.wraps(base)
    def method(self: Any, slave: Any, *args: Any, **kwargs: Any) -> Any:
        unit = _tcp_unit(slave, broadcasting)
        if unit is None:
            return base(self, slave, *args, **kwargs)
        token = _UNIT.set(unit)
        try:
            return base(self, _STAND_IN, *args, **kwargs)
        finally:
            _UNIT.reset(token)

    return method


def _async_method(base: Callable[..., Any], broadcasting: bool) -> Callable[..., Any]:
    @functools.wraps(base)
    async def method(self: Any, slave: Any, *args: Any, **kwargs: Any) -> Any:
        unit = _tcp_unit(slave, broadcasting)
        if unit is None:
            return await base(self, slave, *args, **kwargs)
        token = _UNIT.set(unit)
        try:
            return await base(self, _STAND_IN, *args, **kwargs)
        finally:
            _UNIT.reset(token)

    return method


def _unit_of(call: Call) -> tuple[int, bool]:
    """(unit id to send, whether an answer is awaited) of ``call``."""
    unit = _UNIT.get()
    return (call.slave if unit is None else unit), call.decode is not None


class _TcpLine:
    """What the TCP masters answer for a serial master's line properties (one place
    for both): no line, mode "tcp", no silences, no echo; ``retries`` checked."""

    url: str
    _retries: int

    @property
    def retries(self) -> int:
        return self._retries

    @retries.setter
    def retries(self, value: int) -> None:
        self._retries = check_retries(value)

    @property
    def line(self) -> Any:
        raise AttributeError(NO_LINE.format(url=self.url))

    @property
    def mode(self) -> str:
        return MODE

    @property
    def t35(self) -> float:
        return 0.0

    @property
    def echo(self) -> bool:
        return False

    @property
    def broadcast_delay(self) -> float:
        return 0.0


class TcpMaster(_TcpLine, Master):
    """`pyrtu.Master` on a Modbus TCP connection (made by ``Master("tcp://...")``)."""

    def __init__(
        self, port: str, *args: Any, timeout: float = 1.0, retries: int = 0, **kwargs: Any
    ) -> None:
        self._timeout = check_seconds("timeout", timeout, positive=True)
        self._retries = check_retries(retries)
        self._lock = threading.RLock()
        self.url = port
        self._client = TcpClient(port, timeout=self._timeout)

    def _run(self, call: Call) -> Any:
        with self._lock:
            unit, answered = _unit_of(call)
            for attempt in range(self._retries + 1):
                try:
                    answer = self._client.request(unit, call.pdu, answered=answered)
                    break
                except NoResponseError:
                    if attempt == self._retries:
                        raise
            if call.decode is None or answer is None:
                return None
            return call.decode(answer)

    def add_rule(self, function: int, request_rule: Any, response_rule: Any) -> None:
        """Length rules are not needed on TCP (the MBAP length ends every answer)."""

    @property
    def counters(self) -> dict[str, int]:
        return self._client.counters

    @property
    def timeout(self) -> float:
        return self._timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._timeout = check_seconds("timeout", value, positive=True)
        self._client.timeout = self._timeout

    @property
    def last_answer_time(self) -> float | None:
        return self._client.last_answer_time

    def close(self) -> None:
        with self._lock:
            self._client.close()

    def __repr__(self) -> str:
        return f"<pyrtu.Master {self.url} Modbus TCP>"


class AsyncTcpMaster(_TcpLine, AsyncMaster):
    """`pyrtu.aio.AsyncMaster` on a Modbus TCP connection (``AsyncMaster("tcp://...")``);
    connects on the first request."""

    def __init__(
        self,
        port: str,
        *args: Any,
        timeout: float = 1.0,
        retries: int = 0,
        max_in_flight: int = 1,
        **kwargs: Any,
    ) -> None:
        parse_tcp_url(port)  # ValueError now, not at the first request
        self._timeout = check_seconds("timeout", timeout, positive=True)
        self._retries = check_retries(retries)
        self._max_in_flight = max_in_flight
        self.url = port
        self._client: AsyncTcpClient | None = None
        self._connecting: asyncio.Lock | None = None

    async def _connected(self) -> AsyncTcpClient:
        if self._client is None:
            if self._connecting is None:
                self._connecting = asyncio.Lock()
            async with self._connecting:
                if self._client is None:
                    self._client = await AsyncTcpClient.connect(
                        self.url, timeout=self._timeout, max_in_flight=self._max_in_flight
                    )
        return self._client

    async def _run(self, call: Call) -> Any:
        unit, answered = _unit_of(call)  # (before the first await: the caller's context)
        client = await self._connected()
        for attempt in range(self._retries + 1):
            try:
                answer = await client.request(unit, call.pdu, answered=answered)
                break
            except NoResponseError:
                if attempt == self._retries:
                    raise
        if call.decode is None or answer is None:
            return None
        return call.decode(answer)

    async def add_rule(self, function: int, request_rule: Any, response_rule: Any) -> None:
        """Length rules are not needed on TCP (the MBAP length ends every answer)."""

    @property
    def counters(self) -> dict[str, int]:
        return {} if self._client is None else self._client.counters

    @property
    def timeout(self) -> float:
        return self._timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._timeout = check_seconds("timeout", value, positive=True)
        if self._client is not None:
            self._client.timeout = self._timeout

    @property
    def last_answer_time(self) -> float | None:
        return None if self._client is None else self._client.last_answer_time

    async def close(self) -> None:
        if self._client is not None:
            await self._client.close()

    def __repr__(self) -> str:
        return f"<pyrtu.aio.AsyncMaster {self.url} Modbus TCP>"


class RtuTcpMaster(Master):
    """`pyrtu.Master` on ``rtu+tcp://host:port``: RTU frames (CRC kept) on a TCP socket,
    ``t35`` 0 unless given (a socket has no wire timing)."""

    def __init__(self, port: str, *args: Any, t35: float | None = None, **kwargs: Any) -> None:
        super().__init__(rtu_over_tcp(port), *args, t35=0.0 if t35 is None else t35, **kwargs)


class AsyncRtuTcpMaster(AsyncMaster):
    """`pyrtu.aio.AsyncMaster` on ``rtu+tcp://host:port`` (see `RtuTcpMaster`)."""

    def __init__(self, port: str, *args: Any, t35: float | None = None, **kwargs: Any) -> None:
        super().__init__(rtu_over_tcp(port), *args, t35=0.0 if t35 is None else t35, **kwargs)


for _name in _BROADCASTING | _ADDRESSED:
    setattr(TcpMaster, _name, _sync_method(getattr(Master, _name), _name in _BROADCASTING))
    setattr(
        AsyncTcpMaster, _name, _async_method(getattr(AsyncMaster, _name), _name in _BROADCASTING)
    )

TRANSPORTS["sync"].update({"tcp": TcpMaster, RTU_TCP_SCHEME: RtuTcpMaster})
TRANSPORTS["async"].update({"tcp": AsyncTcpMaster, RTU_TCP_SCHEME: AsyncRtuTcpMaster})
