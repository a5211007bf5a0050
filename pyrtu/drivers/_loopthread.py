"""An event loop in a thread of its own, for synchronous callers: `pyrtu.poller.
PollerThread` and ``pyrtu simulate``'s drives (pyrtu/cli/_simulate_many.py).

The loop is `pyrtu.drivers.aio.new_event_loop` (microsecond timers) and the thread's timer
slack is shrunk as `pyrtu.drivers.aio.run` does, so the serial timing of what runs there
is the same as under ``pyrtu.drivers.aio.run``.  ``begin`` runs first (its error is raised
by `LoopThread.start`), then the loop serves until `LoopThread.stop`, then ``end``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from pyrtu.drivers._slack import tighten_this_thread
from pyrtu.drivers.aio import new_event_loop

__all__ = ["LoopThread"]

log = logging.getLogger("pyrtu.drivers")


class LoopThread:
    """``begin()``, then serve until `stop`, then ``end()``, on a loop of its own."""

    def __init__(
        self,
        name: str,
        begin: Callable[[], Awaitable[Any]],
        end: Callable[[], Awaitable[Any]],
        descriptors: int = 0,
    ) -> None:
        self.loop = new_event_loop(descriptors)  # (``descriptors``: as there)
        self._begin, self._end = begin, end
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        #: what ended the loop while it served (a SystemExit or KeyboardInterrupt out
        #: of a callback: nothing else leaves a running loop); None while it serves
        self.died: BaseException | None = None

    def start(self) -> None:
        """Start the thread; returns once ``begin()`` ended, raising what it raised."""
        self._thread.start()
        self._started.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error

    def stop(self) -> None:
        """Run ``end()`` and end the thread (returns when it has ended)."""
        if self._thread.is_alive() and self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
            self._thread.join()

    def call(self, coro: Coroutine[Any, Any, Any], timeout: float | None = None) -> Any:
        """Run ``coro`` on the loop and wait for its result (or its error)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def _main(self) -> None:
        tighten_this_thread()
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_until_complete(self._body())
        except BaseException as exc:  # logged and kept: `died` is for the thread's owner
            self.died = exc
            log.error("thread %s: its event loop ended", self._thread.name, exc_info=exc)
            # the tasks it left are the owner's to report (`died`): to the log only
            self.loop.set_exception_handler(
                lambda _loop, context: log.debug("after the loop ended: %s", context)
            )
        finally:
            self._started.set()  # whatever happened, start() does not wait forever
            self.loop.close()

    async def _body(self) -> None:
        self._stop = asyncio.Event()
        try:
            await self._begin()
        except BaseException as exc:
            self._error = exc
            return
        finally:
            self._started.set()
        try:
            await self._stop.wait()
        finally:
            await self._end()
