"""The gateway's sans-I/O parts: its limits, the routes (unit id -> bus) and the
fair queue of each bus.  See `pyrtu.gateway` for the whole."""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from pyrtu.core._text import number_ranges
from pyrtu.core.timing import check_seconds
from pyrtu.drivers.reconnect import Backoff
from pyrtu.security.policy import Identity

#: Defaults of the limits (documented in the README and ``pyrtu gateway --help``).
MAX_CONNECTIONS = 64
MAX_QUEUED_PER_CONNECTION = 16
MAX_QUEUED_PER_BUS = 256
MAX_WRITE_BUFFER = 256 * 1024
CLOSE_GRACE = 5.0
#: a request begun (its first byte read) must be complete within this many seconds
HEADER_TIMEOUT = 5.0
#: a connection with no complete request (and nothing waiting for it) for this long
#: is closed
IDLE_TIMEOUT = 120.0


def _positive_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be a positive integer, not {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be a positive integer, not {value!r}")
    return value


@dataclass(frozen=True)
class GatewayLimits:
    """Bounds on what the gateway holds (validated on construction)."""

    max_connections: int = MAX_CONNECTIONS
    max_queued_per_connection: int = MAX_QUEUED_PER_CONNECTION
    max_queued_per_bus: int = MAX_QUEUED_PER_BUS
    max_write_buffer: int = MAX_WRITE_BUFFER
    #: seconds a connection the gateway closes (a malformed header) has to take the
    #: answers still unsent to it; then it is reset
    close_grace: float = CLOSE_GRACE
    #: seconds from the first byte of a request (its MBAP header) to its last; a
    #: connection that takes longer is closed (0: no limit)
    header_timeout: float = HEADER_TIMEOUT
    #: seconds a connection may stay without a complete request while nothing of
    #: its is queued, on a bus or unsent; then it is closed (0: no limit)
    idle_timeout: float = IDLE_TIMEOUT
    #: how a bus whose port failed is retried (`pyrtu.drivers.reconnect.Backoff`)
    backoff: Backoff = field(default_factory=Backoff)

    def __post_init__(self) -> None:
        for name in (
            "max_connections",
            "max_queued_per_connection",
            "max_queued_per_bus",
            "max_write_buffer",
        ):
            _positive_int(name, getattr(self, name))
        for name in ("close_grace", "header_timeout", "idle_timeout"):
            check_seconds(name, getattr(self, name))
        if not isinstance(self.backoff, Backoff):
            raise TypeError(
                f"backoff must be a pyrtu.drivers.reconnect.Backoff, not {self.backoff!r}"
            )


def check_listen(host: object, port: object) -> tuple[str, int]:
    """(host, port) to listen on; TypeError/ValueError naming the argument."""
    if not isinstance(host, str):
        raise TypeError(f"host must be a string, not {type(host).__name__}")
    if isinstance(port, bool) or not isinstance(port, int):
        raise TypeError(f"port must be an integer 0..65535, not {port!r}")
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be 0..65535 (0: any free port), not {port}")
    return host, port


# -- routing ---------------------------------------------------------------------


def parse_units(text: str) -> frozenset[int]:
    """Serial addresses from ``"1-10,20,30-31"`` (1..247; 0 is the broadcast)."""
    ranges = number_ranges(
        text,
        1,
        247,
        not_a_range="unit ids: {part!r} is not a number or a range A-B",
        outside="unit ids: {part!r} is outside 1..247 or not ascending",
    )
    return frozenset(unit for units in ranges for unit in units)


class Routes:
    """Unit id -> (bus index, slave address); every unit on at most one bus.

    Per bus: unit ids (the unit id is the slave address) or a mapping unit id ->
    slave address (a TCP server maps 0xFF, "the server itself", to its device).
    Unit 0 is the broadcast, sent to every bus, unless a mapping routes it to a
    slave address (``{0: 1}``: unit 0 is then answered by slave 1)."""

    def __init__(self, units_per_bus: Sequence[Iterable[int] | Mapping[int, int]]) -> None:
        self._route: dict[int, tuple[int, int]] = {}
        for index, units in enumerate(units_per_bus):
            pairs = units.items() if isinstance(units, Mapping) else ((u, u) for u in units)
            for unit, slave in pairs:
                if not 0 <= unit <= 255:
                    raise ValueError(f"unit id {unit} is outside 0..255")
                if not 1 <= slave <= 247:
                    raise ValueError(f"unit id {unit}: slave address {slave} is outside 1..247")
                if unit in self._route:
                    raise ValueError(
                        f"unit id {unit} is on bus {self._route[unit][0]} and bus {index}"
                    )
                self._route[unit] = (index, slave)
        self.buses = len(units_per_bus)

    def route(self, unit: int) -> tuple[int, int] | None:
        """(bus index, slave address) of a unit id, or None when no bus carries it."""
        return self._route.get(unit)


# -- the fair queue (sans-I/O) -------------------------------------------------------


@dataclass(slots=True)
class Job:
    """A request waiting for (or on) a bus."""

    conn: int  # connection id
    transaction: int
    unit: int  # the unit id of the request (copied into the answer)
    slave: int  # the address on the bus
    pdu: bytes
    #: who sent it (for the audit trail of writes)
    who: Identity | None = None


class QueueFull(Exception):
    """The connection's or the bus's queue is full (answered with exception 0x06)."""


class FairQueue:
    """Requests of many connections for one bus, served round-robin by connection."""

    def __init__(self, max_per_connection: int, max_total: int) -> None:
        self.max_per_connection = max_per_connection
        self.max_total = max_total
        self._queues: OrderedDict[int, deque[Job]] = OrderedDict()
        self._total = 0

    def __len__(self) -> int:
        return self._total

    def queued(self, conn: int) -> int:
        q = self._queues.get(conn)
        return len(q) if q else 0

    def submit(self, job: Job) -> None:
        """Queue ``job``; `QueueFull` when a bound would be passed."""
        if self._total >= self.max_total:
            raise QueueFull(f"{self._total} requests wait for this bus")
        q = self._queues.get(job.conn)
        if q is None:
            q = self._queues[job.conn] = deque()
        elif len(q) >= self.max_per_connection:
            raise QueueFull(f"connection {job.conn} has {len(q)} requests waiting")
        q.append(job)
        self._total += 1

    def pop(self) -> Job | None:
        """The next job: the head of the connection whose turn it is."""
        if not self._queues:
            return None
        queues = self._queues
        conn = next(iter(queues))
        q = queues[conn]
        job = q.popleft()
        self._total -= 1
        if q:
            queues.move_to_end(conn)  # to the back of the round
        else:
            del queues[conn]
        return job

    def drop(self, conn: int) -> int:
        """Forget every job of ``conn``; returns how many."""
        q = self._queues.pop(conn, None)
        n = len(q) if q else 0
        self._total -= n
        return n


def exception_pdu(function: int, code: int) -> bytes:
    return bytes(((function | 0x80) & 0xFF, code))
