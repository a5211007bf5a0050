"""What the poller keeps of one bus while it runs (`BusRun`): its configuration,
scheduler, back-off, master, the writes and reads waiting on it, the transaction in
flight, its place in the start and its wake-up grid.  `pyrtu.poller.driver.Poller`
makes one per bus; its bus task and, for a bus on the mux, `pyrtu.poller.muxdrive`
work on it."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass, field
from typing import Any

from pyrtu.drivers.reconnect import Reconnect

from .config import Bus
from .masters import AsyncMasterLike
from .schedule import BusScheduler, ScheduledRequest


@dataclass
class BusRun:
    """One bus of a running poller (see the module docstring)."""

    bus: Bus
    sched: BusScheduler
    reconnect: Reconnect
    master: AsyncMasterLike | None = None
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    pending: dict[int, asyncio.Future[Any]] = field(default_factory=dict)
    task: asyncio.Task[None] | None = None
    worked: bool = False  # a transaction went through the port since start
    values: int = 0  # values read on this bus since start
    task_failures: int = 0  # times the bus task raised (each restarted) since start
    # the transaction the bus task is in, and the write or read waiting on it
    inflight: ScheduledRequest | None = None
    inflight_future: asyncio.Future[Any] | None = None
    #: the host a network bus connects to (None: a local port)
    host: str | None = None
    #: when a network bus may first connect (monotonic seconds; the start's stagger)
    start_at: float = 0.0
    #: a network bus's polls wake on this grid of the monotonic clock (seconds; 0:
    #: at their due time), so that buses due within one tick share one wake-up
    tick: float = 0.0
    #: the bus's transactions run on the poller's mux (`pyrtu.poller.muxdrive`)
    on_mux: bool = False

    @property
    def port(self) -> str:
        return str(self.bus.port)

    def wake_at(self, deadline: float) -> float:
        """When the bus wakes for something due at ``deadline``: a network bus's
        next grid point of its `tick` at or after it, a local bus's ``deadline``."""
        tick = self.tick
        if not tick or not math.isfinite(deadline):
            return deadline
        # (a deadline a rounding error past a grid point wakes on that point: max)
        return max(deadline, math.ceil(deadline / tick - 1e-6) * tick)

    def port_state(self) -> str:
        """``down`` (an outage is on), ``up`` (a transaction went through and none
        failed since) or ``unknown`` (nothing went through yet)."""
        if self.reconnect.down:
            return "down"
        return "up" if self.worked else "unknown"


__all__ = ["BusRun"]
