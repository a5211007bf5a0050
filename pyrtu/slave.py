"""The Modbus slave (server) over a serial line, RTU or ASCII.

::

    store = pyrtu.DataStore()
    store.holding_registers.add_range(0, [0] * 100)
    with pyrtu.Slave("/dev/ttyUSB1", address=1, store=store, parity="E") as slave:
        slave.start()          # background thread; or slave.serve_forever()
        ...

Shared-bus behaviour: the framer (slave role) sizes every frame on the line,
requests and other slaves' responses alike, so a response is never taken for a
request.  The slave stays silent for other addresses, for frames with a bad
CRC/LRC, and for broadcasts (slave 0), which it executes when they are writes.
It answers no sooner than t3.5 after the end of the request (``t35=0``: no
wait) plus ``response_delay``.  With ``echo=True`` (an adapter that echoes)
the frame equal to what it just sent is dropped.

The diagnostic counters, event log and listen-only mode of the serial line
(FC 08, 11, 12) are per port (`pyrtu._slave_diag.LineState`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from . import _backend
from . import pdu as P
from ._slave_diag import DeviceIdentification, LineState
from ._version import __version__
from .ascii import AsciiFramer, encode_ascii
from .datastore import DataStore
from .errors import SlaveException
from .frames import FrameKind
from .port import Port, open_port
from .rules import LengthRule, RuleTable, check_rules

log = logging.getLogger("pyrtu.slave")
_monotonic = time.monotonic

Handler = Callable[["Slave", int, bytes], "bytes | None"]
_Builtin = Callable[[int, bytes], "bytes | None"]

STANDARD_FUNCTIONS = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43})
_POLL = 0.05  # longest blocking read: stop() and the watchdog react within it


def _addresses(address: int | Iterable[int]) -> frozenset[int]:
    items = [address] if isinstance(address, int) else list(address)
    for a in items:
        if isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= 247:
            raise ValueError(f"a slave address is 1..247, not {a!r}")
    if not items:
        raise ValueError("a slave needs at least one address")
    return frozenset(items)


class Slave:
    """A Modbus slave serving one or several addresses on one port."""

    def __init__(
        self,
        port: Any,
        address: int | Iterable[int] = 1,
        store: DataStore | Mapping[int, DataStore] | None = None,
        *,
        baudrate: int = 19200,
        parity: str = "E",
        stopbits: float = 1,
        bytesize: int = 8,
        mode: str = "rtu",
        echo: bool = False,
        rs485: Any = None,
        t15: float | None = None,
        t35: float | None = None,
        timing: str = "modbus",
        rules: RuleTable | None = None,
        max_adu: int = 256,
        strict: bool = False,
        backend: str | None = None,
        functions: Iterable[int] | None = None,
        identification: dict[int, bytes] | None = None,
        response_delay: float = 0.0,
        watchdog: float | None = None,
        on_watchdog: Callable[[Slave], object] | None = None,
        server_id: bytes = b"pyrtu",
        run_indicator: bool = True,
        exclusive: bool = True,
    ) -> None:
        if mode not in ("rtu", "ascii"):
            raise ValueError(f"mode must be 'rtu' or 'ascii', not {mode!r}")
        self.mode = mode
        self.addresses = _addresses(address)
        self.store: DataStore | Mapping[int, DataStore] = DataStore() if store is None else store
        if isinstance(self.store, Mapping):
            missing = self.addresses - set(self.store)
            if missing:
                raise ValueError(f"store: no DataStore for address(es) {sorted(missing)}")
        self.functions = set(STANDARD_FUNCTIONS if functions is None else functions)
        if (
            isinstance(response_delay, bool)
            or not isinstance(response_delay, int | float)
            or response_delay < 0
        ):
            raise ValueError(
                f"response_delay must be a non-negative number of seconds, not {response_delay!r}"
            )
        self.response_delay = float(response_delay)
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
        self._rules = dict(check_rules(rules))
        self._max_adu = max_adu
        max_pdu = min(P.MAX_PDU, max_adu - 3) if mode == "rtu" else P.MAX_PDU
        self.identification = DeviceIdentification(identification, max_pdu, __version__)
        self.line = LineState()
        self._handlers: dict[int, _Builtin] = self._builtins()
        self._broadcast_ok = set(P.BROADCAST_FUNCTIONS)
        self._hooks: list[Callable[[int, bytes], object]] = []
        self._framer_args: dict[str, Any] = dict(
            parity=parity, stopbits=stopbits, bytesize=bytesize, timing=timing,
            t15=t15, t35=t35, strict=strict, max_adu=max_adu,
        )  # fmt: skip
        self._framer = self._new_framer(baudrate, parity, stopbits, bytesize)  # checks options
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
        self._framer = self._new_framer(p.baudrate, p.parity, p.stopbits, p.bytesize)
        be = self._backend
        t = be.char_timing(p.baudrate, p.parity, p.stopbits, p.bytesize, timing, t15, t35)
        #: the silence kept after a request before answering (seconds; 0: none)
        self.t35 = float(t.t35) if mode == "rtu" else 0.0
        # Damaged messages are told apart by the spec's t3.5 (whatever t35 says).
        spec = be.char_timing(p.baudrate, p.parity, p.stopbits, p.bytesize, timing)
        self.line.boundary = float(spec.t35) if mode == "rtu" else 1.0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serving = False
        self._sent: bytes | None = None
        self._sent_until = 0.0
        self._last_valid: float | None = None
        self._tripped = False
        self._counters = dict.fromkeys(
            [
                "requests",
                "responses",
                "exceptions",
                "broadcasts",
                "ignored",
                "echo_dropped",
                "watchdog_trips",
            ],
            0,
        )
        #: the error that ended serve_forever in the background thread, if any
        self.error: BaseException | None = None

    # ----------------------------------------------------------------- set-up

    def _new_framer(self, baudrate: int, parity: str, stopbits: float, bytesize: int) -> Any:
        self._framer_args.update(parity=parity, stopbits=stopbits, bytesize=bytesize)
        self._baudrate = baudrate
        if self.mode == "ascii":
            return AsciiFramer("slave")
        return self._backend.Framer(
            "slave", baudrate=baudrate, rules=self._rules, **self._framer_args
        )

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
        with self._lock:
            if request_rule is not None or response_rule is not None:
                self._rules.update(check_rules({function: (request_rule, response_rule)}))
                p = self.port
                self._framer = self._new_framer(self._baudrate, p.parity, p.stopbits, p.bytesize)
            self._handlers[function] = lambda unit, pdu: handler(self, unit, pdu)
            self.functions.add(function)
            if broadcast:
                self._broadcast_ok.add(function)
            else:
                self._broadcast_ok.discard(function)

    def on_request(self, callback: Callable[[int, bytes], object]) -> None:
        """Call ``callback(unit, pdu)`` for every valid request addressed to this slave
        (unit 0: broadcast), before it is executed; it may raise `SlaveException`."""
        self._hooks.append(callback)

    def store_for(self, unit: int) -> DataStore:
        """The DataStore that serves ``unit``."""
        if isinstance(self.store, Mapping):
            return self.store[unit]
        return self.store

    @property
    def counters(self) -> dict[str, int]:
        """Requests, responses, exceptions, broadcasts, ignored frames, the serial-line
        diagnostic counters (FC 08), the event counter (FC 11) and watchdog trips."""
        with self._lock:
            out = dict(self._counters)
            out.update(self.line.counters)
            out["event_counter"] = self.line.event_counter
            return out

    @property
    def listen_only(self) -> bool:
        return self.line.listen_only

    @property
    def busy(self) -> bool:
        return self.line.busy

    @busy.setter
    def busy(self, value: bool) -> None:
        self.line.busy = bool(value)

    # ------------------------------------------------------------------ loop

    def serve_forever(self) -> None:
        """Serve requests until `stop` is called."""
        with self._lock:
            if self._serving:
                raise RuntimeError("this slave is already serving")
            self._serving = True
        try:
            while not self._stop.is_set():
                self.poll(_POLL)
        finally:
            self._serving = False

    def start(self) -> Slave:
        """Serve in a background (daemon) thread."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("this slave is already started")
        self._stop.clear()
        self.error = None
        self._thread = threading.Thread(
            target=self._run, name=f"pyrtu-slave {self.port.name}", daemon=True
        )
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self.serve_forever()
        except BaseException as exc:  # kept for the owner; the thread ends
            self.error = exc
            log.error("slave on %s stopped: %s", self.port.name, exc)

    def stop(self, timeout: float = 2.0) -> None:
        """Stop serving (returns within the poll interval, 50 ms)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            self._thread = None

    def close(self) -> None:
        self.stop()
        self.port.close()

    def __enter__(self) -> Slave:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<pyrtu.Slave {sorted(self.addresses)} on {self.port.name} {self.mode}>"

    def poll(self, timeout: float = _POLL) -> None:
        """One step of the loop: wait up to ``timeout`` for bytes, act on what came."""
        framer = self._framer
        now = _monotonic()
        wait = timeout
        timer = framer.timer()
        if timer is not None:
            wait = min(wait, max(0.0, timer - now))
        if self.watchdog is not None and self._last_valid is not None and not self._tripped:
            wait = min(wait, max(0.0, self._last_valid + self.watchdog - now))
        chunk = self.port.read(wait)
        now = _monotonic()
        with self._lock:
            framer = self._framer
            if chunk:
                if self.mode == "ascii" and self.line.ascii_delimiter != 0x0A:
                    chunk = chunk.translate(_delimiter_table(self.line.ascii_delimiter))
                framer.receive_data(chunk, now)
            timer = framer.timer()
            if timer is not None and now >= timer:
                framer.handle_timer(now)
            self._drain_events()
            self._check_watchdog()

    def _check_watchdog(self) -> None:
        if self.watchdog is None or self._last_valid is None or self._tripped:
            return
        if _monotonic() - self._last_valid >= self.watchdog:
            self._tripped = True
            self._counters["watchdog_trips"] += 1
            log.warning(
                "watchdog: no valid telegram for %.3f s on %s", self.watchdog, self.port.name
            )
            if self.on_watchdog is not None:
                try:
                    self.on_watchdog(self)
                except Exception:
                    log.exception("on_watchdog callback failed")

    def _drain_events(self) -> None:
        framer = self._framer
        if self.mode == "rtu":
            while (ev := framer.next_event()) is not None:
                if ev.error is not None:
                    self.line.discard_seen(ev.error.value, ev.start, ev.end)
                else:
                    self._on_frame(ev.kind, ev.adu, ev.adu[:-2], ev.end)
        else:
            while (item := framer.next_event()) is not None:
                frame, message = item
                if message is None:
                    reason = frame.error.value if frame.error else "truncated"
                    self.line.discard_seen(reason, frame.start, frame.end)
                else:
                    self._on_frame(frame.kind, frame.adu, message, frame.end)

    def _on_frame(self, kind: FrameKind, raw: bytes, message: bytes, end: float) -> None:
        if self._sent is not None:
            sent, self._sent = self._sent, None
            if raw == sent and _monotonic() <= self._sent_until:
                self._counters["echo_dropped"] += 1
                return
        self.line.frame_seen()
        if kind is not FrameKind.REQUEST:
            return
        unit = message[0]
        if unit != 0 and unit not in self.addresses:
            self._counters["ignored"] += 1
            return
        broadcast = unit == 0
        request = message[1:]
        self.line.request_received(broadcast)
        self._counters["broadcasts" if broadcast else "requests"] += 1
        self._last_valid = _monotonic()
        self._tripped = False
        if log.isEnabledFor(logging.DEBUG):
            log.debug("RX unit %d: %s", unit, raw.hex(" "))
        if self.line.listen_only:
            if request[:3] == b"\x08\x00\x01":  # restart: the one request served
                with contextlib.suppress(SlaveException):  # not answered either way
                    self.line.diagnostics(request)
            self.line.not_answered()
            return
        response = self._execute(unit, request)
        if broadcast or response is None:
            self.line.not_answered()
            return
        self._respond(unit, response, end)

    def _execute(self, unit: int, request: bytes) -> bytes | None:
        fc = request[0]
        try:
            for hook in self._hooks:
                hook(unit, request)
            handler = self._handlers.get(fc)
            if handler is None or fc not in self.functions:
                raise SlaveException(1, f"function {fc} is not supported")
            if unit == 0:
                if fc not in self._broadcast_ok:
                    return None
                units = self._broadcast_units(fc)
            else:
                units = [unit]
            response = None
            for u in units:
                with self.store_for(u).lock if u else _NoLock():
                    response = handler(u, request)
            self.line.completed(fc)
            return response
        except SlaveException as exc:
            if unit:
                log.debug("unit %d function %d: exception %d (%s)", unit, fc, exc.code, exc)
            return P.exception_response(fc, exc.code)
        except Exception:
            log.exception("unit %d function %d: handler failed", unit, fc)
            return P.exception_response(fc, 4)

    def _broadcast_units(self, fc: int) -> list[int]:
        if fc not in P.BROADCAST_FUNCTIONS:
            return [0]  # a registered handler: called once with unit 0
        seen: set[int] = set()
        units = []
        for u in sorted(self.addresses):
            store = self.store_for(u)
            if id(store) not in seen:
                seen.add(id(store))
                units.append(u)
        return units

    def _respond(self, unit: int, response: bytes, request_end: float) -> None:
        message = bytes((unit,)) + response
        adu = self._backend.add_crc(message) if self.mode == "rtu" else encode_ascii(message)
        earliest = request_end + self.t35 + self.response_delay
        delay = earliest - _monotonic()
        if delay > 0:
            time.sleep(delay)
        if self.mode == "rtu":
            self._framer.send(adu)
        self._sent = adu if self.echo else None
        _start, end = self.port.write(adu)
        # the echo comes back within its own wire time (and some adapter latency)
        self._sent_until = end + 2 * len(adu) * self.port.char_time + 0.2
        exception = response[1] if response[0] & 0x80 else None
        self.line.answered(exception)
        self._counters["exceptions" if exception is not None else "responses"] += 1
        if log.isEnabledFor(logging.DEBUG):
            log.debug("TX unit %d: %s", unit, adu.hex(" "))

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
            17: lambda unit, pdu: P.server_id_response(
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
        address, count = P.decode_read(pdu)
        store = self.store_for(unit)
        table = store.coils if pdu[0] == P.READ_COILS else store.discrete_inputs
        return P.bits_response(pdu[0], [bool(v) for v in table.read(address, count)])

    def _read_registers(self, unit: int, pdu: bytes) -> bytes:
        address, count = P.decode_read(pdu)
        store = self.store_for(unit)
        table = (
            store.holding_registers if pdu[0] == P.READ_HOLDING_REGISTERS else store.input_registers
        )
        return P.registers_response(pdu[0], [int(v) for v in table.read(address, count)])

    def _write_single(self, unit: int, pdu: bytes) -> bytes:
        address, value = P.decode_write_single(pdu)
        store = self.store_for(unit)
        if pdu[0] == P.WRITE_SINGLE_COIL:
            store.coils.write(address, [value == P.COIL_ON])
        else:
            store.holding_registers.write(address, [value])
        return pdu

    def _write_multiple(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        if pdu[0] == P.WRITE_MULTIPLE_COILS:
            address, bits = P.decode_write_coils(pdu)
            store.coils.write(address, list(bits))
        else:
            address, words = P.decode_write_registers(pdu)
            store.holding_registers.write(address, list(words))
        return pdu[:5]

    def _mask_write(self, unit: int, pdu: bytes) -> bytes:
        address, and_mask, or_mask = P.decode_mask_write(pdu)
        table = self.store_for(unit).holding_registers
        current = int(table.read(address, 1)[0])
        table.write(address, [(current & and_mask) | (or_mask & ~and_mask & 0xFFFF)])
        return pdu

    def _read_write(self, unit: int, pdu: bytes) -> bytes:
        raddr, rcount, waddr, words = P.decode_read_write(pdu)
        table = self.store_for(unit).holding_registers
        table.check_read(raddr, rcount)
        table.write(waddr, list(words))
        return P.registers_response(pdu[0], [int(v) for v in table.read(raddr, rcount)])

    def _read_fifo(self, unit: int, pdu: bytes) -> bytes:
        address = P.decode_fifo(pdu)
        table = self.store_for(unit).holding_registers
        count = int(table.read(address, 1)[0])
        if count > P.MAX_FIFO:
            raise SlaveException(3, f"read_fifo_queue: {count} entries at {address} (at most 31)")
        values = [int(v) for v in table.read(address + 1, count)] if count else []
        return P.fifo_response(values)

    def _read_file(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        records = []
        for file, record, length in P.decode_read_file(pdu):
            records.append([int(v) for v in store.file(file).read(record, length)])
        return P.read_file_response(records)

    def _write_file(self, unit: int, pdu: bytes) -> bytes:
        store = self.store_for(unit)
        items = P.decode_write_file(pdu)
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
        read_code, object_id = P.decode_device_id(pdu)
        return P.device_id_response(self.identification.page(read_code, object_id))


class _NoLock:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None


_TABLES: dict[int, bytes] = {}


def _delimiter_table(char: int) -> bytes:
    """Incoming bytes with ``char`` as the frame end (FC 08 sub-function 0x03)."""
    table = _TABLES.get(char)
    if table is None:
        mapping = bytearray(range(256))
        mapping[char] = 0x0A
        mapping[0x0A] = 0x00  # a LF is no longer a delimiter: it breaks the frame
        table = _TABLES[char] = bytes(mapping)
    return table


__all__ = ["STANDARD_FUNCTIONS", "Handler", "Slave"]
