"""`PollerThread`: a `Poller` on an event loop of its own in a background thread,
for synchronous scripts (``Poller.running()``)."""

from __future__ import annotations

import queue
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from typing import Any, Protocol

from pyrtu.drivers._loopthread import LoopThread

from .events import BusReport, Update
from .points import Value

_QUEUE = 65536


class _Poller(Protocol):
    """What the thread facade uses of `pyrtu.poller.Poller` (which imports this
    module for ``Poller.running()``; this one does not import it back)."""

    _update_cbs: list[Callable[[Update], None]]

    @property
    def descriptors(self) -> int: ...

    def start(self) -> Coroutine[Any, Any, None]: ...
    def stop(self) -> Coroutine[Any, Any, None]: ...
    def values(self) -> dict[str, Value | None]: ...
    def latest(self) -> dict[str, Update]: ...
    def age(self, name: str) -> float | None: ...
    def report(self) -> list[BusReport]: ...
    def summary(self) -> dict[str, Any]: ...
    def write(self, name: str, value: object) -> Awaitable[str]: ...
    def read(self, name: str) -> Awaitable[Value | None]: ...
    def on_update(self, callback: Callable[[Update], None]) -> None: ...


class PollerThread:
    """A `Poller` on its own asyncio loop in a background thread, for scripts::

    with Poller(config).running() as p:
        p.values(); p.write("pump.reference", 30.0); p.report()
    """

    def __init__(self, poller: _Poller) -> None:
        self.poller = poller
        self._thread = LoopThread(
            "pyrtu-poller", poller.start, poller.stop, descriptors=poller.descriptors
        )
        self._loop = self._thread.loop  # microsecond timers (see pyrtu.drivers.aio)

    def start(self) -> PollerThread:
        """Start the thread; raises what `Poller.start` raised (not a port that
        fails: that is a `PortState` event, and retried)."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the poller and end the thread (returns within about one timeout)."""
        self._thread.stop()

    def __enter__(self) -> PollerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _await(self, coro: Any, timeout: float | None = None) -> Any:
        return self._thread.call(coro, timeout)

    def values(self) -> dict[str, Value | None]:
        return self.poller.values()

    def latest(self) -> dict[str, Update]:
        return self.poller.latest()

    def age(self, name: str) -> float | None:
        return self.poller.age(name)

    def report(self) -> list[BusReport]:
        return self._await(self._call(self.poller.report))  # type: ignore[no-any-return]

    def summary(self) -> dict[str, Any]:
        return self._await(self._call(self.poller.summary))  # type: ignore[no-any-return]

    @staticmethod
    async def _call(fn: Callable[[], Any]) -> Any:
        return fn()

    def write(self, name: str, value: object, timeout: float | None = None) -> str:
        """Write a point (ahead of the polls) and wait for the answer; returns how
        (`Poller.write`)."""
        return self._await(self.poller.write(name, value), timeout)  # type: ignore[no-any-return]

    def read(self, name: str, timeout: float | None = None) -> Value | None:
        """Read a point now (ahead of the polls)."""
        return self._await(self.poller.read(name), timeout)  # type: ignore[no-any-return]

    def updates(self, timeout: float | None = None) -> Iterator[Update]:
        """Delivered values as they come; stops after ``timeout`` seconds without one
        (None: never)."""
        q: queue.Queue[Update | None] = queue.Queue(_QUEUE)

        def put(u: Update) -> None:
            if q.full():
                q.get_nowait()
            q.put_nowait(u)

        self._loop.call_soon_threadsafe(self.poller.on_update, put)
        try:
            while True:
                try:
                    item = q.get(timeout=timeout)
                except queue.Empty:
                    return
                if item is None:
                    return
                yield item
        finally:
            self._loop.call_soon_threadsafe(self._remove, put)

    def _remove(self, cb: Callable[[Update], None]) -> None:
        if cb in self.poller._update_cbs:
            self.poller._update_cbs.remove(cb)


__all__ = ["PollerThread"]
