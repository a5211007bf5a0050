"""One schedule for reopening what failed: a serial port, a TCP connection, a broker.

Sans-I/O, time is an input: the driver calls `failed(now, error)` when an open or an
I/O call fails, asks `due(now)` (or sleeps until `retry_at`) before the next attempt,
and calls `recovered(now)` when an attempt works.  The first `failed` of an outage
returns True, so the driver reports it exactly once (an event and one log line), not
once per retry; `recovered` hands back the `Outage` that ended, for the "back after"
report.  Waits between attempts grow from `initial` by `factor` up to `maximum`, each
spread by +-`jitter` (a fraction) so that many ports that failed together do not
retry in step.  Used by the poller, the gateway and ``pyrtu simulate`` alike.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

from pyrtu.core.timing import check_seconds


@dataclass(frozen=True)
class Backoff:
    """How long to wait between attempts to reopen: `initial` doubling to `maximum`."""

    initial: float = 0.5
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.1

    def __post_init__(self) -> None:
        check_seconds("initial", self.initial, True)
        check_seconds("maximum", self.maximum, True)
        if self.maximum < self.initial:
            raise ValueError(f"maximum ({self.maximum}) must be >= initial ({self.initial})")
        if isinstance(self.factor, bool) or not isinstance(self.factor, (int, float)):
            raise TypeError(f"factor must be a number, not {type(self.factor).__name__}")
        if not 1.0 <= self.factor < math.inf:
            raise ValueError(f"factor must be a finite number >= 1, got {self.factor!r}")
        if isinstance(self.jitter, bool) or not isinstance(self.jitter, (int, float)):
            raise TypeError(f"jitter must be a number, not {type(self.jitter).__name__}")
        if not 0.0 <= self.jitter < 1.0:
            raise ValueError(f"jitter must be in [0, 1), got {self.jitter!r}")

    def delay(self, attempt: int, rng: random.Random | None = None) -> float:
        """The wait after failed attempt number `attempt` (1 = the first failure)."""
        base = min(self.maximum, self.initial * self.factor ** max(0, attempt - 1))
        if not self.jitter:
            return base
        r = (rng or random).uniform(-self.jitter, self.jitter)
        return min(self.maximum, base * (1.0 + r))


@dataclass(frozen=True)
class Outage:
    """One outage of a resource, from its first failure to the attempt that worked."""

    since: float
    error: str
    attempts: int
    until: float | None = None

    @property
    def duration(self) -> float | None:
        return None if self.until is None else self.until - self.since


class Reconnect:
    """The retry state of one resource (see the module docstring)."""

    def __init__(self, backoff: Backoff | None = None, rng: random.Random | None = None) -> None:
        self.backoff = backoff or Backoff()
        self._rng = rng
        self._outage: Outage | None = None
        self._retry_at: float | None = None
        self.outages = 0  # how many outages began, for statistics

    @property
    def down(self) -> bool:
        return self._outage is not None

    @property
    def outage(self) -> Outage | None:
        return self._outage

    @property
    def retry_at(self) -> float | None:
        """When the next attempt is due (None while up)."""
        return self._retry_at

    def failed(self, now: float, error: BaseException | str) -> bool:
        """An open or I/O call failed at `now`; True if this begins an outage (report it)."""
        text = error if isinstance(error, str) else (str(error) or type(error).__name__)
        first = self._outage is None
        if first:
            self._outage = Outage(since=now, error=text, attempts=1)
            self.outages += 1
        else:
            assert self._outage is not None
            o = self._outage
            self._outage = Outage(since=o.since, error=text, attempts=o.attempts + 1)
        self._retry_at = now + self.backoff.delay(self._outage.attempts, self._rng)
        return first

    def due(self, now: float) -> bool:
        """Whether an attempt may be made now (always while up)."""
        return self._retry_at is None or now >= self._retry_at

    def wait(self, now: float) -> float:
        """Seconds until the next attempt is due (0 while up or when due)."""
        return 0.0 if self._retry_at is None else max(0.0, self._retry_at - now)

    def recovered(self, now: float) -> Outage | None:
        """An attempt worked at `now`: the outage that ended (None if there was none)."""
        o, self._outage, self._retry_at = self._outage, None, None
        if o is None:
            return None
        return Outage(since=o.since, error=o.error, attempts=o.attempts, until=now)
