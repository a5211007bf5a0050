"""The part every drive simulator shares: its data store, clock, lock, the lazy
time line, the serial supervision, and the binding to `pyrtu.Slave` (or, for many drives
in one event loop, `pyrtu.drivers.aio.AsyncSlave`)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Generic, TypeVar

from pyrtu.core.rules import LengthRule
from pyrtu.drivers.aio_slave import AsyncSlave
from pyrtu.drivers.slave import Slave
from pyrtu.protocol.datastore import DataStore, Table

from .motor import Clock, Motor, Supervision, Timeline, monotonic

Handler = Callable[[Slave, int, bytes], "bytes | None"]
#: (handler, request rule, response rule, executed when broadcast)
HandlerSpec = tuple[Handler, LengthRule | None, LengthRule | None, bool]
InputsT = TypeVar("InputsT", bound=tuple[object, ...])


class Outputs(Generic[InputsT]):
    """Registers a simulator computes from its model, kept in ``table``:
    ``compute(inputs)`` gives their values (address -> value) from ``inputs`` (a tuple
    of everything they depend on) alone.  `show` computes them again only when the
    inputs changed, and writes them again only when the inputs or the table's values
    (`Table.version`) changed since it last wrote them."""

    def __init__(self, table: Table, compute: Callable[[InputsT], Mapping[int, int]]) -> None:
        self.table = table
        self.compute = compute
        self.values: Mapping[int, int] = {}
        self._inputs: InputsT | None = None
        self._version = -1

    def show(self, inputs: InputsT) -> None:
        """Make the table show the values of ``inputs`` (under the table's lock)."""
        if inputs != self._inputs:
            self.values = self.compute(inputs)
            self._inputs = inputs
        elif self.table.version == self._version:
            return  # the table still holds them
        self.table.set_each(self.values)
        self._version = self.table.version


class DriveSimulator(ABC):
    """Base class: a drive model behind a `DataStore`, evaluated lazily.

    Subclasses implement `_retarget` (commands -> motor reference), `_refresh`
    (model -> registers) and `slave_options`, and extend `_trip` (the watchdog
    expired), `_on_telegram` and `_served_at`.
    Every public method takes the store's lock, so a simulator can be observed from
    any thread while its `pyrtu.Slave` serves the bus.
    """

    #: name used by `pyrtu simulate` and the registry
    device = ""
    #: the manual's addresses for its worked examples
    example_addresses: frozenset[int] = frozenset({1})
    #: the transmission modes the manual gives
    modes: tuple[str, ...] = ("rtu",)

    def __init__(self, *, mode: str = "rtu", clock: Clock = monotonic) -> None:
        self.mode = self._check_mode(mode)
        self.store = DataStore()
        self.lock = self.store.lock
        self.clock = clock
        self.timeline = Timeline(clock)
        self.motor = Motor()
        self.supervision = Supervision()
        self.slave: Slave | AsyncSlave | None = None
        #: valid telegrams addressed to this drive (every one restarts the watchdog)
        self.telegrams = 0
        #: how often the serial watchdog expired
        self.watchdog_trips = 0
        #: the address `make_slave` serves (None: not served, or several addresses)
        self.served_address: int | None = None

    # -- time -----------------------------------------------------------------------

    def update(self, now: float | None = None) -> float:
        """Bring the model to ``now`` (default: the clock); returns the time."""
        with self.lock:
            t = self._run(now)
            self._refresh()
            return t

    def _run(self, now: float | None) -> float:
        """The model (not yet the registers) to ``now`` (None: the clock)."""
        return self.timeline.run(now, self._next_event, self._advance, self._fire)

    def _next_event(self) -> float | None:
        return self.supervision.deadline()

    def _advance(self, dt: float) -> None:
        self.motor.advance(dt)

    def _fire(self, at: float) -> None:
        deadline = self.supervision.deadline()
        if deadline is not None and deadline <= at:
            self.supervision.tripped = True
            self._trip(at)

    def _trip(self, at: float) -> None:
        """The watchdog expired at ``at`` (subclasses add the drive's reaction)."""
        self.watchdog_trips += 1

    @abstractmethod
    def _retarget(self) -> None:
        """Commands and parameters -> the motor's reference and ramps."""

    @abstractmethod
    def _refresh(self) -> None:
        """The model -> the values a master reads."""

    def ramp_time_left(self) -> float:
        """Seconds until the motor reaches its present reference (inf: never)."""
        with self.lock:
            self.update()
            t = self.motor.time_to_reference()
            return t if math.isfinite(t) else math.inf

    def frequency_hz(self) -> float:
        """The motor's output frequency now, in Hz (negative: reverse)."""
        with self.lock:
            self.update()
            return self.motor.frequency

    # -- telegrams ------------------------------------------------------------------

    def telegram(self, unit: int = 0, pdu: bytes = b"") -> None:
        """A valid telegram for this drive arrived (the slave's ``on_request``): the
        model to now, the drive's reaction, then the registers (once)."""
        with self.lock:
            now = self._run(None)
            self._on_telegram(now, unit, pdu)
            self.supervision.feed(now)
            self._refresh()

    def _on_telegram(self, now: float, unit: int, pdu: bytes) -> None:
        """A valid telegram at ``now``, before the watchdog restarts and the registers
        follow the model (subclasses extend)."""
        self.telegrams += 1

    def _check_mode(self, mode: str) -> str:
        if mode not in self.modes:
            raise ValueError(
                f"{type(self).__name__}: the manual gives the {' and '.join(self.modes)} "
                f"mode{'s' if len(self.modes) > 1 else ''} only, not {mode!r}"
            )
        return mode

    # -- the slave --------------------------------------------------------------------

    @abstractmethod
    def slave_options(self) -> dict[str, Any]:
        """Keywords for `pyrtu.Slave` that make it this drive (functions, limits,
        identification, response delay, vendor rules)."""

    def handlers(self) -> Mapping[int, HandlerSpec]:
        """Function codes this drive handles itself: ``fc -> (handler, request_rule,
        response_rule, broadcast)`` for `pyrtu.Slave.register_function`."""
        return {}

    def make_slave(self, port: Any, address: int | Iterable[int] = 1, **options: Any) -> Slave:
        """A `pyrtu.Slave` on ``port`` serving this drive (not started).  ``options``
        are `pyrtu.Slave` keywords (baudrate, parity, ...); they override the drive's
        own (`slave_options`).  ``mode`` switches the drive to RTU or ASCII (where
        its manual has both)."""
        addr, kwargs = self._slave_arguments(address, options)
        slave = Slave(port, addr, self.store, **kwargs)
        self._bind(slave, address)
        return slave

    def make_async_slave(
        self, port: Any, address: int | Iterable[int] = 1, **options: Any
    ) -> AsyncSlave:
        """`make_slave` for asyncio: an `AsyncSlave` (serve it with ``await
        slave.serve()`` or ``slave.start()``); many drives share one event loop."""
        addr, kwargs = self._slave_arguments(address, options)
        slave = AsyncSlave(port, addr, self.store, **kwargs)
        self._bind(slave, address)
        return slave

    def _slave_arguments(
        self, address: int | Iterable[int], options: dict[str, Any]
    ) -> tuple[int | set[int], dict[str, Any]]:
        if "mode" in options:
            self.mode = self._check_mode(options.pop("mode"))
        kwargs = self.slave_options()
        kwargs.update(options)
        addr: int | set[int] = address if isinstance(address, int) else set(address)
        return addr, kwargs

    def _bind(self, slave: Slave | AsyncSlave, address: int | Iterable[int]) -> None:
        for fc, (handler, req, resp, broadcast) in self.handlers().items():
            slave.register_function(fc, handler, req, resp, broadcast=broadcast)
        slave.on_request(self.telegram)
        self.slave = slave
        if isinstance(address, int):
            with self.lock:
                self._served_at(address)

    def _served_at(self, address: int) -> None:
        """The slave serves ``address`` (subclasses keep it in the drive's parameter)."""
        self.served_address = address

    def serve(self, port: Any, address: int | Iterable[int] = 1, **options: Any) -> Slave:
        """`make_slave` and start it in a background thread; returns the slave."""
        slave = self.make_slave(port, address, **options)
        slave.start()
        return slave

    def close(self) -> None:
        """Close the `Slave` (an `AsyncSlave` is only let go: its owner awaits its
        ``close()``)."""
        if isinstance(self.slave, Slave):
            self.slave.close()
        self.slave = None

    def __enter__(self) -> DriveSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
