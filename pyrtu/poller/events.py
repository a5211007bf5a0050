"""What a poller reports: value updates, port and slave state changes, dropped
points, overload, a bus task that failed; and the per-point, per-slave and per-bus figures.

Every event but `Update` has ``as_dict()``: its ``pyrtu poll --json`` line, with an
``"event"`` key naming its kind (``"port"``, ``"slave"``, ``"dropped"``,
``"overload"``, ``"task_failed"``); an update's line has none (``{"point", "value", "time", "slave",
"bus"}``, and ``"quality": "bad"`` with value null when the device said "no value")."""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, NamedTuple

from .points import Point, Value
from .values import faithful_value


class _FlatEvent:
    """An event whose JSON form is ``"event"`` (``EVENT``), then its fields as they
    are, in their order."""

    __slots__ = ()
    EVENT: ClassVar[str]

    def as_dict(self) -> dict[str, Any]:
        values = {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]
        return {"event": self.EVENT, **values}


@dataclass(frozen=True, slots=True)
class Update:
    """A point's value, stamped with the time the answer's last byte arrived; value
    None: the device answered its "no value" marker (the point's ``error_value`` or
    ``unsupported_value``, a BCD digit above 9): quality ``bad``."""

    point: Point
    value: Value | None
    time: float

    @property
    def quality(self) -> str:
        """``good``, or ``bad`` when the device said "no value"."""
        return "bad" if self.value is None else "good"

    @property
    def name(self) -> str:
        return self.point.name

    def as_dict(self) -> dict[str, Any]:
        """The JSON form of ``pyrtu poll --json`` (the value as its shortest faithful
        decimal, `pyrtu.poller.values`)."""
        p = self.point
        doc = {"point": p.name, "value": faithful_value(p, self.value), "time": self.time,
               "slave": p.slave, "bus": p.bus}  # fmt: skip
        if self.value is None:
            doc["quality"] = "bad"
        return doc


@dataclass(frozen=True, slots=True)
class SlaveState(_FlatEvent):
    """A slave went online (answered again) or offline (stopped answering)."""

    EVENT = "slave"

    bus: str
    slave: int
    online: bool
    time: float


@dataclass(frozen=True, slots=True)
class PortState(_FlatEvent):
    """A bus's port failed or works again.

    ``up`` False: the port could not be opened (connected), or failed in use (a
    drop unplugged, a TCP peer gone); reported once per outage, with the first
    ``error``, while the poller retries with back-off.  ``up`` True: a transaction
    went through again; ``error`` is the outage's last error, ``attempts`` how many
    attempts failed.  ``since``: when the outage began (``time.time()`` clock, like
    ``time``)."""

    EVENT = "port"

    bus: str
    port: str
    up: bool
    error: str
    since: float
    attempts: int
    time: float


@dataclass(frozen=True, slots=True)
class PointDropped:
    """A point that can never be read (exception 2 on its own): reported once and
    taken out of the schedule."""

    point: Point
    reason: str
    time: float

    def as_dict(self) -> dict[str, Any]:
        p = self.point
        return {"event": "dropped", "point": p.name, "slave": p.slave, "bus": p.bus,
                "reason": self.reason, "time": self.time}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Overload:
    """The configured rates of a bus need ``load`` times the wire (> 1), or no longer
    do (``overloaded`` False); ``lagging`` names the points that miss their interval."""

    bus: str
    overloaded: bool
    load: float
    lagging: tuple[str, ...]
    time: float

    def as_dict(self) -> dict[str, Any]:
        return {"event": "overload", "bus": self.bus, "overloaded": self.overloaded,
                "load": round(self.load, 4), "lagging": list(self.lagging),
                "time": self.time}  # fmt: skip


@dataclass(frozen=True, slots=True)
class TaskFailed:
    """A bus's task raised something unexpected (a fault of the poller, not of the
    port or the slaves): ``error`` is its cause (``"Type: message"``); the task
    starts again in ``retry_in`` seconds (the bus's back-off) while the other buses
    poll on.  Reported once per run of failures; every failure is counted in the
    bus's ``task_failures``."""

    bus: str
    task: str
    error: str
    retry_in: float
    time: float

    def as_dict(self) -> dict[str, Any]:
        return {"event": "task_failed", "bus": self.bus, "task": self.task, "error": self.error,
                "retry_in": round(self.retry_in, 3), "time": self.time}  # fmt: skip


Event = Update | PortState | SlaveState | PointDropped | Overload | TaskFailed


class Unchanged(NamedTuple):
    """Not an event of the API: what a scheduler says (for the driver alone) when a
    poll block answered exactly the registers (or bits) of its previous answer.
    Decoding is a function of them, so none of its points changed: nothing to
    decode, nothing to deliver when only changes are (the driver's `Tracker.reread`
    notes the read); ``data`` and ``address`` decode them where every sample is
    delivered.  (A named tuple: one is made for nearly every poll.)"""

    points: tuple[Point, ...]
    data: Sequence[int] | Sequence[bool]
    address: int
    time: float

    def updates(self) -> list[Update]:
        """The points' samples, as the block's answer gives them."""
        data, address, stamp = self.data, self.address, self.time
        return [Update(p, p.decode(data, address), stamp) for p in self.points]


def percentile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank percentile (``q`` in 0..100) of sorted values; None if empty."""
    if not sorted_values:
        return None
    rank = max(1, -(-len(sorted_values) * q // 100))
    return sorted_values[int(rank) - 1]


#: the fields of `SlaveStats` its dict shows as they are, in this order
_SLAVE_COUNTS = ("bus", "slave", "requests", "responses", "timeouts", "exceptions", "frame_errors")


#: how many of a slave's latest latencies its percentiles are taken over
LATENCY_WINDOW = 1024


@dataclass
class SlaveStats:
    """Counts of one slave's transactions, the wire time they took (``busy``,
    seconds) and their latencies (``latencies``: seconds, the latest last; the
    percentiles are of the last `LATENCY_WINDOW`, and at most twice that many are
    kept, 8 bytes each: `note_latency`)."""

    bus: str
    slave: int
    requests: int = 0
    responses: int = 0
    timeouts: int = 0
    exceptions: int = 0
    frame_errors: int = 0
    online: bool | None = None
    busy: float = 0.0
    latencies: array[float] = field(default_factory=lambda: array("d"))

    @property
    def success_rate(self) -> float | None:
        return self.responses / self.requests if self.requests else None

    def note_latency(self, seconds: float) -> None:
        """An answered transaction's latency; the oldest go in bulk, when twice the
        window is reached (a thousand devices keep no float object per answer)."""
        latencies = self.latencies
        latencies.append(seconds)
        if len(latencies) >= 2 * LATENCY_WINDOW:
            del latencies[:-LATENCY_WINDOW]

    def latency(self, q: float) -> float | None:
        """The ``q`` percentile (nearest rank) of the last `LATENCY_WINDOW` latencies."""
        return percentile(sorted(self.latencies[-LATENCY_WINDOW:]), q)

    def as_dict(self) -> dict[str, Any]:
        p50, p99 = self.latency(50), self.latency(99)
        state = {None: "unknown", True: "online", False: "offline"}[self.online]
        rate = self.success_rate
        return {
            **{name: getattr(self, name) for name in _SLAVE_COUNTS},
            "state": state,
            "busy_s": round(self.busy, 4),
            "success_rate": None if rate is None else round(rate, 4),
            "latency_p50_ms": None if p50 is None else round(p50 * 1e3, 3),
            "latency_p99_ms": None if p99 is None else round(p99 * 1e3, 3),
        }


@dataclass(frozen=True, slots=True)
class BusReport:
    """A bus's figures: ``utilisation`` is wire-busy time over wall time since the
    statistics started; ``load`` the wire time the configured rates ask for per
    second (> 1: more than the wire carries); ``lagging`` the points that miss
    their interval."""

    bus: str
    utilisation: float
    load: float
    overloaded: bool
    lagging: tuple[str, ...]
    transactions: int
    seconds: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "bus": self.bus,
            "utilisation": round(self.utilisation, 4),
            "load": round(self.load, 4),
            "overloaded": self.overloaded,
            "lagging": list(self.lagging),
            "transactions": self.transactions,
            "seconds": round(self.seconds, 3),
        }


class Tracker:
    """Change-only delivery and per-point age.  `offer` records a sample and says
    whether it is to be delivered (first value, or a change beyond the point's
    deadband)."""

    def __init__(self) -> None:
        self._delivered: dict[str, Value | None] = {}
        self._seen: dict[str, float] = {}
        self._latest: dict[str, Update] = {}
        #: the stamp of a point's latest read when it came after its latest sample in
        #: ``_latest`` (`reread`: the value again, no `Update` made for it)
        self._reread: dict[str, float] = {}
        #: a block's points reread together (`reread` with the same ``points``
        #: tuple): [points, seen, stamp] shared by them, moved once per read
        self._groups: dict[int, list[Any]] = {}
        self._group_of: dict[str, list[Any]] = {}

    def offer(self, update: Update, seen: float) -> bool:
        """``seen``: the sample's time on the clock `age` is asked on."""
        point = update.point
        name, new = point.name, update.value
        self._seen[name] = seen
        self._latest[name] = update
        delivered = self._delivered
        if name in delivered:
            old = delivered[name]
            # the common case first: the value delivered last, again (no change
            # under any deadband: `Point.changed` is False for an equal value)
            if (type(old) is type(new) and old == new) or not point.changed(old, new):
                return False
        delivered[name] = new
        return True

    def reread(self, points: Sequence[Point], seen: float, stamp: float) -> None:
        """``points`` read again with the values of their latest samples (a block that
        answered what it answered before: `Unchanged`), at ``stamp``; ``seen`` as in
        `offer`.  Nothing to deliver: only their age and their latest sample's time
        move on."""
        group = self._groups.get(id(points))
        if group is not None and group[0] is points:  # (the same block as before)
            group[1], group[2] = seen, stamp
            return
        seen_at, reread = self._seen, self._reread
        for p in points:
            seen_at[p.name] = seen
            reread[p.name] = stamp
        if type(points) is tuple:  # the points follow the tuple's next rereads
            group = [points, seen, stamp]
            self._groups[id(points)] = group
            for p in points:
                self._group_of[p.name] = group

    def _seen_at(self, name: str) -> float | None:
        """When point ``name`` was last read on the `age` clock (None: never)."""
        t = self._seen.get(name)
        group = self._group_of.get(name)
        if group is not None and t is not None and group[1] > t:
            return float(group[1])
        return t

    def _current(self, update: Update) -> Update:
        """``update`` (a point's latest sample) with the time of a later `reread`."""
        name = update.point.name
        stamp = self._reread.get(name)
        group = self._group_of.get(name)
        if group is not None and (stamp is None or group[2] > stamp):
            stamp = group[2]
        if stamp is None or stamp <= update.time:
            return update
        return Update(update.point, update.value, stamp)

    def age(self, name: str, now: float) -> float | None:
        """Seconds since the point was last read (None: never)."""
        t = self._seen_at(name)
        return None if t is None else now - t

    def latest(self) -> dict[str, Update]:
        """The last sample of every point read so far."""
        current = self._current
        return {name: current(u) for name, u in self._latest.items()}

    def last(self, name: str) -> Update | None:
        """The last sample of one point (None: never read)."""
        update = self._latest.get(name)
        return None if update is None else self._current(update)

    def __len__(self) -> int:
        """How many points were read at least once."""
        return len(self._latest)


__all__ = [
    "BusReport",
    "Event",
    "Overload",
    "PointDropped",
    "PortState",
    "SlaveState",
    "SlaveStats",
    "TaskFailed",
    "Tracker",
    "Update",
    "percentile",
]
