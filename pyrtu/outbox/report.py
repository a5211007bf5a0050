"""Report by exception, with qualities (sans-I/O: time is an input).

The poller hands over every value it reads; `Reporter` says which of them to
publish: the first of a point, one that differs from the last published beyond
the point's ``deadband``, one whose quality changes (``stale`` back to ``good``;
``bad`` when the device answers the point's "no value" marker, its ``error_value``),
and an unchanged one whose last publication is ``max_age`` old (0: never).  When a
slave goes offline every one of its points is published again as ``stale`` (the
last value read and when it was read: never a last good value passed off as live),
and a point the poller drops (it cannot be read) as ``bad``; the same ``stale``
for every point of a bus whose port fails (`bus_down`: an outage says nothing of
the slaves, but the values are no longer live).  A point never read has no last
value: its ``stale`` carries value None and time None (never a time of 1970).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from ..poller import Point
from ..poller.points import Value


@dataclass(slots=True)
class _State:
    point: Point
    max_age: float
    value: Value | None = None  # the last value read
    time: float | None = None  # when it was read (Unix time; None: never)
    published: Value | None = None
    published_at: float = -1e300  # the reporter's clock
    quality: str = ""  # of the last publication ("": none yet)


#: what to publish: (point, value, time read (None: never read), quality)
Report = tuple[Point, Value | None, float | None, str]


class Reporter:
    """Which values to publish (see the module docstring)."""

    def __init__(self, points: Iterable[Point], max_age: Mapping[str, float]) -> None:
        self._s = {p.name: _State(p, max_age.get(p.name, 0.0)) for p in points}
        self._by_slave: dict[tuple[str, int], list[_State]] = {}
        for s in self._s.values():
            self._by_slave.setdefault((s.point.bus, s.point.slave), []).append(s)

    def update(
        self, point: Point, value: Value | None, time: float, now: float, exact: bool = False
    ) -> bool:
        """A value read at ``time`` (Unix) and seen at ``now`` (any clock): whether
        to publish it (as ``good``; value None, the device's "no value" marker, as
        ``bad`` when the quality changes); ``exact``: any change, whatever the
        deadband (a write's read-back), but never the value last published again."""
        s = self._s[point.name]
        s.value = value
        s.time = time
        quality = "bad" if value is None else "good"
        if (
            s.quality != quality
            or (
                value is not None
                and (_differs(s.published, value) if exact else point.changed(s.published, value))
            )
            or (s.max_age > 0 and now - s.published_at >= s.max_age)
        ):
            s.published = value
            s.published_at = now
            s.quality = quality
            return True
        return False

    def slave_state(self, bus: str, slave: int, online: bool, now: float) -> list[Report]:
        """A slave went offline: every one of its points as ``stale``.  Online: nothing
        now; each point's next value is published (its quality changes)."""
        if online:
            return []
        return self._stale(self._by_slave.get((bus, slave), ()), now)

    def bus_down(self, bus: str, now: float) -> list[Report]:
        """The bus's port failed: every point of the bus as ``stale`` (each point's
        next value, after the port is back, is published as ``good``)."""
        mine = (s for (b, _), states in self._by_slave.items() if b == bus for s in states)
        return self._stale(mine, now)

    @staticmethod
    def _stale(states: Iterable[_State], now: float) -> list[Report]:
        out: list[Report] = []
        for s in states:
            if s.quality in ("bad", "stale"):
                continue
            s.quality = "stale"
            s.published_at = now
            out.append((s.point, s.value, s.time, "stale"))
        return out

    def dropped(self, point: Point, time: float, now: float) -> Report:
        """The point cannot be read (found out at ``time``, Unix): ``bad``, value null."""
        s = self._s[point.name]
        s.quality = "bad"
        s.published = None
        s.published_at = now
        return (point, None, time, "bad")

    def quality(self, name: str) -> str:
        """The quality last published for a point ("" before the first)."""
        return self._s[name].quality

    def last(self, name: str) -> tuple[Value | None, float | None]:
        """The last value read of a point and when (None, None: never)."""
        s = self._s[name]
        return s.value, s.time


def _differs(old: Value | None, new: Value) -> bool:
    """Whether ``new`` is another value than ``old`` (NaN equals NaN)."""
    if old is None or type(old) is not type(new):
        return True
    if isinstance(new, float) and isinstance(old, float) and math.isnan(new):
        return not math.isnan(old)
    return new != old


__all__ = ["Report", "Reporter"]
