"""Shared drive physics for the simulators: clocks, a ramped motor, serial supervision.

Nothing here does I/O.  Time is always passed in (seconds, monotonic) or read from an
injectable clock, so tests can step a `ManualClock` and check exact values.

The model is evaluated lazily: a simulator calls ``update(now)`` whenever its state is
observed (a request arrives, a register is read, the owner asks), and the model moves
from the last evaluation to ``now`` in one piece, stopping at every event on the way
(a watchdog deadline, the motor reaching its reference) so that an action taken at an
event (a ramp stop, a fault) starts at the right moment.  Ramps are linear, so each
piece is exact: no time step, no drift.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

#: A clock: returns seconds, monotonic.
Clock = Callable[[], float]


def monotonic() -> float:
    """The default clock (`time.monotonic`)."""
    return time.monotonic()


class ManualClock:
    """A clock for tests: stands still until `advance` or `set` moves it."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._now

    def advance(self, seconds: float) -> float:
        """Move the clock forward by ``seconds`` (>= 0); returns the new time."""
        if seconds < 0:
            raise ValueError("a clock cannot go backwards")
        with self._lock:
            self._now += seconds
            return self._now

    def set(self, now: float) -> None:
        """Move the clock to ``now`` (not earlier than the current time)."""
        with self._lock:
            if now < self._now:
                raise ValueError("a clock cannot go backwards")
            self._now = float(now)


def _rate(span: float, seconds: float) -> float:
    """Hz/s for a ramp that covers ``span`` Hz in ``seconds`` (0 s: a step)."""
    if seconds <= 0:
        return math.inf
    return span / seconds


@dataclass
class Motor:
    """Output frequency following a reference along linear ramps.

    ``frequency`` and ``reference`` are signed Hz (negative = reverse).  Moving away from
    zero uses ``accel`` (Hz/s), moving towards zero uses ``decel``; a change of
    direction decelerates to zero first, then accelerates.  ``math.inf`` is a step.
    """

    accel: float = 10.0
    decel: float = 10.0
    frequency: float = 0.0
    reference: float = 0.0

    @classmethod
    def from_times(cls, span_hz: float, accel_s: float, decel_s: float) -> Motor:
        """Ramps given as times over ``span_hz`` (e.g. 0 to maximum frequency)."""
        return cls(_rate(span_hz, accel_s), _rate(span_hz, decel_s))

    def set_ramp_times(self, span_hz: float, accel_s: float, decel_s: float) -> None:
        """Set the ramps as times to cover ``span_hz``."""
        self.accel = _rate(span_hz, accel_s)
        self.decel = _rate(span_hz, decel_s)

    @property
    def at_reference(self) -> bool:
        return self.frequency == self.reference

    def _leg(self, f: float) -> tuple[float, float]:
        """(goal, rate) of the straight piece of the ramp that starts at ``f`` Hz.

        A piece never crosses zero, so ``|frequency|`` is monotonic along it."""
        r = self.reference
        if f == 0.0 or (f > 0) == (r > 0):
            if abs(r) >= abs(f) and r != 0.0:
                return r, self.accel
            return r, self.decel
        return 0.0, self.decel  # reversing: down to zero first

    def _legs(self) -> list[tuple[float, float, float]]:
        """The pieces (start, goal, rate) from the present output to the reference."""
        legs: list[tuple[float, float, float]] = []
        f = self.frequency
        while f != self.reference and len(legs) < 3:
            goal, rate = self._leg(f)
            legs.append((f, goal, rate))
            f = goal
        return legs

    @staticmethod
    def _span(a: float, b: float, rate: float) -> float:
        return 0.0 if rate == math.inf else abs(b - a) / rate

    def time_to(self, level: float) -> float:
        """Seconds until ``|frequency|`` first equals ``level`` on the way to the
        reference (0 if it already does; ``math.inf`` if it never will)."""
        if abs(self.frequency) == level:
            return 0.0
        total = 0.0
        for start, goal, rate in self._legs():
            a, b = abs(start), abs(goal)
            if min(a, b) <= level <= max(a, b):
                return total + self._span(a, level, rate)
            total += self._span(start, goal, rate)
        return math.inf

    def time_to_reference(self) -> float:
        """Seconds until the output reaches the reference."""
        return sum(self._span(s, g, r) for s, g, r in self._legs())

    def advance(self, dt: float) -> None:
        """Move the output ``dt`` seconds along the ramps."""
        while self.frequency != self.reference:
            goal, rate = self._leg(self.frequency)
            if rate == math.inf:
                self.frequency = goal
                continue
            if dt <= 0.0:
                return
            need = abs(goal - self.frequency) / rate
            if need <= dt:
                self.frequency = goal
                dt -= need
            else:
                self.frequency += math.copysign(rate * dt, goal - self.frequency)
                dt = 0.0

    def coast(self) -> None:
        """Output off at once (the motor coasts; the drive reports 0 Hz)."""
        self.frequency = 0.0


@dataclass
class Supervision:
    """Serial communication watchdog (WEG P314, Bonfiglioli 413).

    ``timeout`` seconds (0 = off).  Counting starts at the first valid telegram after
    power-up; every valid telegram restarts it.  `deadline` is when it trips, or None.
    """

    timeout: float = 0.0
    last: float | None = None
    tripped: bool = False

    def feed(self, now: float) -> None:
        """A valid telegram arrived at ``now``."""
        self.last = now

    def deadline(self) -> float | None:
        if self.timeout <= 0 or self.last is None or self.tripped:
            return None
        return self.last + self.timeout

    def reset(self) -> None:
        """Back to the power-up state: not counting until the next valid telegram."""
        self.last = None
        self.tripped = False


@dataclass
class Timeline:
    """Runs a drive model from its last evaluation up to ``now``, event by event.

    The owner supplies ``next_event(now) -> float | None`` (the earliest pending event
    time, or None), ``advance(dt)`` (move the continuous state) and
    ``fire(at) -> None`` (handle what is due at ``at``).
    """

    clock: Clock = monotonic
    now: float = field(default=0.0)

    def __post_init__(self) -> None:
        self.now = self.clock()

    def run(
        self,
        now: float | None,
        next_event: Callable[[], float | None],
        advance: Callable[[float], None],
        fire: Callable[[float], None],
    ) -> float:
        target = self.clock() if now is None else now
        target = max(target, self.now)
        for _ in range(1000):
            at = next_event()
            if at is None or at > target:
                break
            at = max(at, self.now)
            advance(at - self.now)
            self.now = at
            fire(at)
        advance(target - self.now)
        self.now = target
        return target
