"""What the sync `Slave` and the asyncio `AsyncSlave` share: their options, the
function table (the standard functions over the `DataStore`, FC 07/08/11/12/17/43,
vendor handlers) and the server protocol they drive (`pyrtu.protocol.server`).

A driver subclasses `SlaveBase`, opens its port, calls `_setup_line` and then only
moves bytes and times between the port and ``self.protocol``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from pyrtu import pdu as pdus
from pyrtu._version import __version__
from pyrtu.core import _backend
from pyrtu.core._forward import Forward, Settable
from pyrtu.core.framing import check_core_limits
from pyrtu.core.line import LINE_DEFAULTS, LineConfig, LineKeywords, adopt_port_format, line_from
from pyrtu.core.rules import LengthRule, check_rules
from pyrtu.core.timing import check_seconds
from pyrtu.drivers.port import Port, open_line_port
from pyrtu.pdu.errors import SlaveException
from pyrtu.protocol.datastore import DataStore
from pyrtu.protocol.diagnostics import DeviceIdentification, LineState
from pyrtu.protocol.server import ServerProtocol

if TYPE_CHECKING:  # Unpack is in typing from Python 3.11 (annotations only)
    from typing import Unpack

log = logging.getLogger("pyrtu.drivers.slave")

Handler = Callable[[Any, int, bytes], "bytes | None"]
_Builtin = Callable[[int, bytes], "bytes | None"]

STANDARD_FUNCTIONS = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43})

S = TypeVar("S")


class SlaveKeywords(LineKeywords, Generic[S], total=False):
    """The keywords of `pyrtu.Slave` and `pyrtu.drivers.aio.AsyncSlave` (``S``: the class the
    watchdog callback receives): the line keywords, the port's (``rs485``,
    ``exclusive``: `pyrtu.drivers.port.open_port`) and the slave's, whose defaults are those
    of `SlaveBase`."""

    echo: bool
    rs485: Any
    backend: str | None
    functions: Iterable[int] | None
    identification: dict[int, bytes] | None
    response_delay: float
    watchdog: float | None
    on_watchdog: Callable[[S], object] | None
    server_id: bytes
    run_indicator: bool
    exclusive: bool


#: the keywords a driver passes on to `open_line_port`, and those of `SlaveBase`
_PORT_KEYS = ("rs485", "exclusive")
_SLAVE_KEYS = frozenset(SlaveKeywords.__annotations__) - set(LINE_DEFAULTS) - set(_PORT_KEYS)


def _addresses(address: int | Iterable[int]) -> frozenset[int]:
    items = [address] if isinstance(address, int) else list(address)
    for a in items:
        if isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= 247:
            raise ValueError(f"a slave address is 1..247, not {a!r}")
    if not items:
        raise ValueError("a slave needs at least one address")
    return frozenset(items)


class SlaveBase:
    """A Modbus slave serving one or several addresses on one port (driver-neutral)."""

    port: Port
    protocol: ServerProtocol

    def __init__(
        self,
        address: int | Iterable[int] = 1,
        store: DataStore | Mapping[int, DataStore] | None = None,
        *,
        line: LineConfig,
        echo: bool = False,
        backend: str | None = None,
        functions: Iterable[int] | None = None,
        identification: dict[int, bytes] | None = None,
        response_delay: float = 0.0,
        watchdog: float | None = None,
        on_watchdog: Callable[[Any], object] | None = None,
        server_id: bytes = b"pyrtu",
        run_indicator: bool = True,
    ) -> None:
        self.line_config = line
        self.mode = line.mode
        self.addresses = _addresses(address)
        self.store: DataStore | Mapping[int, DataStore] = DataStore() if store is None else store
        if isinstance(self.store, Mapping):
            missing = self.addresses - set(self.store)
            if missing:
                raise ValueError(f"store: no DataStore for address(es) {sorted(missing)}")
        self.functions = set(STANDARD_FUNCTIONS if functions is None else functions)
        self.response_delay = check_seconds("response_delay", response_delay)
        if watchdog is not None and (
            isinstance(watchdog, bool) or not isinstance(watchdog, int | float) or watchdog <= 0
        ):
            raise ValueError(
                f"watchdog must be a positive number of seconds or None, not {watchdog!r}"
            )
        self.watchdog = None if watchdog is None else float(watchdog)
        self.on_watchdog = on_watchdog
        if not isinstance(server_id, bytes | bytearray) or len(server_id) > 250:
            raise ValueError(f"server_id must be bytes (at most 250), not {server_id!r}")
        self.server_id = bytes(server_id)
        self.run_indicator = bool(run_indicator)
        #: FC 07: the eight exception status bits (the owner sets them)
        self.exception_status = 0
        self.echo = bool(echo)
        self._backend = _backend.backend(backend)
        max_pdu = min(pdus.MAX_PDU, line.max_adu - 3) if line.mode == "rtu" else pdus.MAX_PDU
        self.identification = DeviceIdentification(identification, max_pdu, __version__)
        self.line = LineState()
        self._handlers: dict[int, _Builtin] = self._builtins()
        self._broadcast_ok = set(pdus.BROADCAST_FUNCTIONS)
        self._hooks: list[Callable[[int, bytes], object]] = []
        if line.mode == "rtu":  # the core's limits, checked before the port is opened
            check_core_limits(line.options("slave"))

    def _setup_line(self, port: Port) -> None:
        """The port is open: the line as the port has it (an adopted serial object
        may differ from the keywords), and the protocol on it."""
        self.port = port
        line = adopt_port_format(self.line_config, port)
        self.line_config = line
        #: the silence kept after a request before answering (seconds; 0: none)
        self.t35 = line.frame_gap
        self.protocol = ServerProtocol(
            line,
            self,
            backend=self._backend,
            state=self.line,
            echo=self.echo,
            response_delay=self.response_delay,
            watchdog=self.watchdog,
        )

    # ------------------------------------------------------------ the owner's API

    def register_function(
        self,
        function: int,
        handler: Handler,
        request_rule: LengthRule | None = None,
        response_rule: LengthRule | None = None,
        *,
        broadcast: bool = False,
    ) -> None:
        """Serve ``function`` with ``handler(slave, unit, pdu) -> response PDU`` (None: no
        answer; raise `SlaveException` for an exception response).  The rules size its
        frames on the bus; ``broadcast=True`` executes it when sent to slave 0."""
        if isinstance(function, bool) or not isinstance(function, int) or not 1 <= function <= 127:
            raise ValueError(f"register_function: function must be 1..127, not {function!r}")
        if not callable(handler):
            raise ValueError(f"register_function: handler must be callable, not {handler!r}")
        with self._guard():
            if request_rule is not None or response_rule is not None:
                rules = dict(self.line_config.rules)
                rules.update(check_rules({function: (request_rule, response_rule)}))
                self.line_config = self.line_config.replace(rules=rules)
                self.protocol.reconfigure(self.line_config)
            self._handlers[function] = lambda unit, pdu: handler(self, unit, pdu)
            self.functions.add(function)
            if broadcast:
                self._broadcast_ok.add(function)
            else:
                self._broadcast_ok.discard(function)

    def _guard(self) -> Any:
        """A context manager around changes the serving side may see (sync: the lock)."""
        return contextlib.nullcontext()

    def on_request(self, callback: Callable[[int, bytes], object]) -> None:
        """Call ``callback(unit, pdu)`` for every valid request addressed to this slave
        (unit 0: broadcast), before it is executed; it may raise `SlaveException`."""
        self._hooks.append(callback)

    def store_for(self, unit: int) -> DataStore:
        """The DataStore that serves ``unit``."""
        store = self.store
        if type(store) is DataStore or not isinstance(store, Mapping):
            return store
        return store[unit]

    @property
    def counters(self) -> dict[str, int]:
        """Requests, responses, exceptions, broadcasts, ignored frames, the serial-line
        diagnostic counters (FC 08), the event counter (FC 11) and watchdog trips."""
        with self._guard():
            out = dict(self.protocol.counters)
            out.update(self.line.counters)
            out["event_counter"] = self.line.event_counter
            return out

    #: listen-only mode (FC 08 sub-function 04 sets it), the line state's flag; read-only
    listen_only = Forward[bool]("line")
    #: the busy status FC 11 and FC 12 report (0xFFFF while set; the owner sets it)
    busy = Settable[bool]("line", bool)

    # --------------------------------------------------- the protocol's application

    def watchdog_expired(self) -> None:
        port = getattr(self, "port", None)
        log.warning("watchdog: no valid telegram on %s", port.name if port else "the line")
        if self.on_watchdog is not None:
            try:
                self.on_watchdog(self)
            except Exception:
                log.exception("on_watchdog callback failed")

    def execute(self, unit: int, request: bytes) -> bytes | None:
        """The response PDU of ``request`` (unit 0: a broadcast), None for no answer.
        Safe from any thread: it runs under the driver's guard (the sync `Slave`'s
        lock), so a slave served on TCP too (`pyrtu.tcp.server`) executes one request
        at a time."""
        with self._guard():
            return self._execute(unit, request)

    def _execute(self, unit: int, request: bytes) -> bytes | None:
        fc = request[0]
        try:
            for hook in self._hooks:
                hook(unit, request)
            handler = self._handlers.get(fc)
            if handler is None or fc not in self.functions:
                raise SlaveException(1, f"function {fc} is not supported")
            if unit:
                with self.store_for(unit).lock:
                    response = handler(unit, request)
            else:
                if fc not in self._broadcast_ok:
                    return None
                response = None
                for u in self._broadcast_units(fc):
                    if u:
                        with self.store_for(u).lock:
                            response = handler(u, request)
                    else:
                        response = handler(u, request)
            self.line.completed(fc)
            return response
        except SlaveException as exc:
            if unit:
                log.debug("unit %d function %d: exception %d (%s)", unit, fc, exc.code, exc)
            return pdus.exception_response(fc, exc.code)
        except Exception:
            log.exception("unit %d function %d: handler failed", unit, fc)
            return pdus.exception_response(fc, 4)

    def _broadcast_units(self, fc: int) -> list[int]:
        if fc not in pdus.BROADCAST_FUNCTIONS:
            return [0]  # a registered handler: called once with unit 0
        seen: set[int] = set()
        units = []
        for u in sorted(self.addresses):
            store = self.store_for(u)
            if id(store) not in seen:
                seen.add(id(store))
                units.append(u)
        return units

    # ---------------------------------------------------------- the functions

    def _builtins(self) -> dict[int, _Builtin]:
        return {
            1: self._read_bits,
            2: self._read_bits,
            3: self._read_registers,
            4: self._read_registers,
            5: self._write_single,
            6: self._write_single,
            7: lambda unit, pdu: bytes((7, self.exception_status & 0xFF)),
            8: lambda unit, pdu: self.line.diagnostics(pdu),
            11: lambda unit, pdu: self.line.event_counter_response(),
            12: lambda unit, pdu: self.line.event_log_response(),
            15: self._write_multiple,
            16: self._write_multiple,
            17: lambda unit, pdu: pdus.server_id_response(
                self.server_id + (b"\xff" if self.run_indicator else b"\x00")
            ),
            20: self._read_file,
            21: self._write_file,
            22: self._mask_write,
            23: self._read_write,
            24: self._read_fifo,
            43: self._device_id,
        }

    def _read_bits(self, unit: int, pdu: bytes) -> bytes:
        address, count = pdus.decode_read(pdu)
        store = self.store_for(unit)
        table = store.coils if pdu[0] == pdus.READ_COILS else store.discrete_inputs
        return pdus.bits_response(pdu[0], [bool(v) for v in table.read(address, count)])

    def _read_registers(self, unit: int, pdu: bytes) -> bytes:
        address, count = pdus.decode_read(pdu)
        store = self.store_for(unit)
        table = (
            store.holding_registers
            if pdu[0] == pdus.READ_HOLDING_REGISTERS
            else store.input_registers
        )
        return pdus.registers_response(pdu[0], [int(v) for v in table.read(address, count)])

    def _write_single(self, unit: int, pdu: bytes) -> bytes:
        address, value = pdus.decode_write_single(pdu)
        store = self.store_for(unit)
        if pdu[0] == pdus.WRITE_SINGLE_COIL:
            store.coils.write(address, [value == pdus.COIL_ON])
        else:
            store.holding_registers.write(address, [value])
        return pdu

    def _write_multiple(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        if pdu[0] == pdus.WRITE_MULTIPLE_COILS:
            address, bits = pdus.decode_write_coils(pdu)
            store.coils.write(address, list(bits))
        else:
            address, words = pdus.decode_write_registers(pdu)
            store.holding_registers.write(address, list(words))
        return pdu[:5]

    def _mask_write(self, unit: int, pdu: bytes) -> bytes:
        address, and_mask, or_mask = pdus.decode_mask_write(pdu)
        table = self.store_for(unit).holding_registers
        current = int(table.read(address, 1)[0])
        table.write(address, [(current & and_mask) | (or_mask & ~and_mask & 0xFFFF)])
        return pdu

    def _read_write(self, unit: int, pdu: bytes) -> bytes:
        raddr, rcount, waddr, words = pdus.decode_read_write(pdu)
        table = self.store_for(unit).holding_registers
        table.check_read(raddr, rcount)
        table.write(waddr, list(words))
        return pdus.registers_response(pdu[0], [int(v) for v in table.read(raddr, rcount)])

    def _read_fifo(self, unit: int, pdu: bytes) -> bytes:
        address = pdus.decode_fifo(pdu)
        table = self.store_for(unit).holding_registers
        count = int(table.read(address, 1)[0])
        if count > pdus.MAX_FIFO:
            raise SlaveException(3, f"read_fifo_queue: {count} entries at {address} (at most 31)")
        values = [int(v) for v in table.read(address + 1, count)] if count else []
        return pdus.fifo_response(values)

    def _read_file(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        records = []
        for file, record, length in pdus.decode_read_file(pdu):
            records.append([int(v) for v in store.file(file).read(record, length)])
        return pdus.read_file_response(records)

    def _write_file(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        items = pdus.decode_write_file(pdu)
        for file, record, values in items:
            store.file(file).check_write(record, list(values))
        before = [(store.file(f), r, store.file(f).get_many(r, len(v))) for f, r, v in items]
        try:
            for file, record, values in items:
                store.file(file).write(record, list(values))
        except SlaveException:
            for table, record, old in before:
                table.set_many(record, old)
            raise
        return pdu

    def _device_id(self, unit: int, pdu: bytes) -> bytes:
        read_code, object_id = pdus.decode_device_id(pdu)
        return pdus.device_id_response(self.identification.page(read_code, object_id))


class PortSlave(SlaveBase, Generic[S]):
    """A slave on a serial port (`pyrtu.Slave`, `pyrtu.drivers.aio.AsyncSlave`): their one
    constructor.  The line comes from ``line=`` or the line keywords, the slave's
    options are checked, the port is opened and the protocol set on it; then the
    driver sets up its own state (`_driver_state`)."""

    #: the constructor's name in the errors about its keywords
    _where = "PortSlave"

    def __init__(
        self,
        port: Any,
        address: int | Iterable[int] = 1,
        store: DataStore | Mapping[int, DataStore] | None = None,
        *,
        line: LineConfig | None = None,
        **options: Unpack[SlaveKeywords[S]],
    ) -> None:
        ports: dict[str, Any] = {k: v for k, v in options.items() if k in _PORT_KEYS}
        slave: dict[str, Any] = {k: v for k, v in options.items() if k in _SLAVE_KEYS}
        keywords = {k: v for k, v in options.items() if k not in _SLAVE_KEYS and k not in ports}
        config = line_from(line, self._where, **keywords)
        super().__init__(address, store, line=config, **slave)
        self._setup_line(open_line_port(port, config, **ports))
        #: sleep through the known rest of a frame (not in strict mode: every gap
        #: counts; not on a port without a file descriptor)
        self._skip = not self.line_config.strict and self.port.fd is not None
        #: the error that ended serving, if any
        self.error: BaseException | None = None
        self._driver_state()

    def _driver_state(self) -> None:
        """The driver's own state, once the port is open (its threads, timers, pipes)."""


__all__ = [
    "STANDARD_FUNCTIONS",
    "Handler",
    "PortSlave",
    "SlaveBase",
    "SlaveKeywords",
]
