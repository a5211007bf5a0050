"""`OutboxService`: what every northbound output (the JSON bridge, the Sparkplug B
edge node) does around its tasks: run for a duration, say when it cannot go on, and
keep its background tasks supervised on the shared back-off."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from pyrtu.core._closing import AsyncService
from pyrtu.drivers.reconnect import Backoff
from pyrtu.drivers.supervise import supervise


class OutboxService(AsyncService):
    """The base of a northbound output.  Each output sets ``_stop`` (an event made by
    its `start`, set when it cannot go on), ``_running``, ``fatal`` (why it halted),
    and defines `_backoff` and `task_failed`."""

    #: how the output names itself in a message ("the bridge", "the edge node")
    WHAT = "the service"
    _stop: asyncio.Event | None
    _running: bool
    fatal: BaseException | None

    def _backoff(self) -> Backoff:
        """The back-off a failed task restarts on."""
        raise NotImplementedError

    def task_failed(
        self, task: str, error: BaseException, retry_in: float, first: bool = True
    ) -> None:
        """A background task raised ``error``; it starts again in ``retry_in`` s."""
        raise NotImplementedError

    async def run(self, duration: float | None = None) -> None:
        """Start, run for ``duration`` seconds (None: until cancelled or a fatal error
        such as refused credentials, raised), stop."""
        await self.start()
        assert self._stop is not None
        try:
            if duration is None:
                await self._stop.wait()
            else:
                try:
                    await asyncio.wait_for(self._stop.wait(), duration)
                except TimeoutError:
                    pass
        finally:
            await self.stop()
        if self.fatal is not None:
            raise self.fatal

    @property
    def halted(self) -> asyncio.Event:
        """Set when the output cannot go on (`fatal` says why); made by `start`."""
        assert self._stop is not None, f"start {self.WHAT} first"
        return self._stop

    def _supervise(
        self,
        name: str,
        body: Callable[[], Awaitable[None]],
        cleanup: Callable[[], None] | None = None,
    ) -> asyncio.Task[None]:
        """Run ``body`` as the task ``name`` under `pyrtu.drivers.supervise`: when it
        raises, report it (`task_failed`), run ``cleanup`` and start it again after
        the shared back-off."""
        return supervise(
            name,
            body,
            lambda f: self.task_failed(f.task, f.error, f.retry_in, f.first),
            backoff=self._backoff(),
            running=lambda: self._running,
            cleanup=cleanup,
        )


__all__ = ["OutboxService"]
