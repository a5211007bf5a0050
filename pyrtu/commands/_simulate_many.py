"""``pyrtu simulate DEVICE --port A --port B ...``: one simulated drive per port, all
served by `pyrtu.aio.AsyncSlave` on one event loop, in one thread of this process.

Many buses (the drops of several ``pyrtu vbus``) then cost one process and one
interpreter instead of one per drive: fewer processes to switch between and less
cache to refill on each wake-up.  The command's main thread keeps its own loop
(signals, ``--duration``, ``--watch``); it starts and stops this one.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import Any

from .._loopthread import LoopThread

__all__ = ["DriveLoop"]


class DriveLoop:
    """Serve ``slaves`` (AsyncSlaves, not started) on a `LoopThread` until `stop`.
    ``error``: the first error that ended a slave (a port that failed or vanished);
    the others go on serving until `stop`."""

    def __init__(self, slaves: Sequence[Any]) -> None:
        self.slaves = list(slaves)
        self.error: BaseException | None = None
        self._thread = LoopThread("pyrtu-simulate", self._begin, self._end)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop every slave and close its port; returns when the thread has ended."""
        self._thread.stop()

    @property
    def counters(self) -> dict[str, int]:
        """The slaves' counters, added up."""
        total: dict[str, int] = {}
        for slave in self.slaves:
            for key, value in slave.counters.items():
                total[key] = total.get(key, 0) + value
        return total

    def _ended(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None and self.error is None:
            self.error = task.exception()

    async def _begin(self) -> None:
        for slave in self.slaves:
            slave.start().add_done_callback(self._ended)

    async def _end(self) -> None:
        for slave in self.slaves:
            try:
                await slave.close()
            except Exception as exc:  # the other slaves are still closed
                self.error = self.error or exc
