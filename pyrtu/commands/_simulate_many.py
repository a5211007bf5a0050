"""``pyrtu simulate DEVICE --port A --port B ...``: one simulated drive per port, all
served by `pyrtu.aio.AsyncSlave` on one event loop, in one thread of this process.

Many buses (the drops of several ``pyrtu vbus``) then cost one process and one
interpreter instead of one per drive: fewer processes to switch between and less
cache to refill on each wake-up.  The command's main thread keeps its own loop
(signals, ``--duration``, ``--watch``); it starts and stops this one.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Sequence
from typing import Any

from ..aio import run as aio_run

__all__ = ["DriveLoop"]

#: how long `DriveLoop.stop` waits for the serving thread
_JOIN = 10.0


class DriveLoop:
    """Serve ``slaves`` (AsyncSlaves, not started) in a thread of their own until
    `stop`.  ``error``: the first error that ended a slave (a port that failed or
    vanished); the others go on serving until `stop`."""

    def __init__(self, slaves: Sequence[Any]) -> None:
        self.slaves = list(slaves)
        self.error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pyrtu-simulate", daemon=True)

    def start(self) -> None:
        self._thread.start()
        self._ready.wait()
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        """Stop every slave and close its port; returns when the thread has ended."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and self._thread.is_alive():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:  # the loop closed in the meantime
                pass
        if self._thread.is_alive():
            self._thread.join(_JOIN)

    @property
    def counters(self) -> dict[str, int]:
        """The slaves' counters, added up."""
        total: dict[str, int] = {}
        for slave in self.slaves:
            for key, value in slave.counters.items():
                total[key] = total.get(key, 0) + value
        return total

    def _run(self) -> None:
        try:
            aio_run(self._main())
        except BaseException as exc:  # pragma: no cover - reported to the main thread
            self.error = self.error or exc
        finally:
            self._ready.set()

    def _ended(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None and self.error is None:
            self.error = task.exception()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        try:
            for slave in self.slaves:
                slave.start().add_done_callback(self._ended)
        finally:
            self._ready.set()
        try:
            await self._stop.wait()
        finally:
            for slave in self.slaves:
                try:
                    await slave.close()
                except Exception as exc:  # the other slaves are still closed
                    self.error = self.error or exc
