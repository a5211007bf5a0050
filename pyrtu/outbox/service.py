"""`OutboxService`: what every northbound output (the JSON bridge, the Sparkplug B
edge node) does around its tasks and its outbox: open the outbox and start the
poller (`_open`), store a point update (`_append`, `publish_value`), run for a
duration, say when it cannot go on, keep its background tasks supervised on the
shared back-off and cancel them at the end (`_cancel_tasks`)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable

from pyrtu.core._closing import AsyncService
from pyrtu.drivers.reconnect import Backoff
from pyrtu.drivers.supervise import supervise

from ..poller import Point, Poller
from ..poller.points import Value
from ._sync import Flusher
from .outbox import Outbox, OutboxError, OutboxLimits
from .report import Reporter
from .updates import PointUpdate, encode_update

log = logging.getLogger("pyrtu.outbox")


class OutboxService(AsyncService):
    """The base of a northbound output.  Each output sets ``poller``, ``reporter``,
    ``_outbox`` and ``_flusher`` (None until `_open`), ``_tasks``, ``_stop`` and
    ``_lost_ev`` (None until `_open`; set when it cannot go on, when its connection
    ends), ``_running``, ``fatal`` (why it halted), and defines `feed`,
    `_backoff`, `task_failed`, `_flushed`, `_stored` and `_store_refused`."""

    #: how the output names itself in a message ("the bridge", "the edge node")
    WHAT = "the service"
    poller: Poller
    reporter: Reporter
    _outbox: Outbox | None
    _flusher: Flusher | None
    _tasks: list[asyncio.Task[None]]
    _stop: asyncio.Event | None
    _lost_ev: asyncio.Event | None
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

    def _flushed(self, error: OutboxError | None) -> None:
        """A batch of the outbox's fsyncs is done (called on the flusher's thread's
        behalf on the loop): ``error`` None, its records are durable."""
        raise NotImplementedError

    def _stored(self, seq: int, rec: bytes, update: PointUpdate) -> None:
        """A point update is in the outbox (`_append`), as record ``seq``: publish it
        when the output may."""
        raise NotImplementedError

    def _store_refused(self, error: Exception) -> None:
        """The outbox refused an update (`OutboxError`: the disk, the budget)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ life cycle

    async def _open(
        self, directory: str, limits: OutboxLimits, poll: bool, opened: Callable[[Outbox], None]
    ) -> None:
        """Open the outbox in ``directory`` (OutboxError when it cannot be) and its
        flusher thread, call ``opened(outbox)``, then start the poller (unless ``poll``
        is False) with its events to ``self.feed``; when the poller cannot start
        (PortError), the outbox is closed again and the error raised."""
        ob = self._outbox = Outbox(directory, limits)
        flusher = self._flusher = Flusher(ob, self._flushed)
        flusher.start()  # the fsyncs on their own thread
        opened(ob)
        self._stop = asyncio.Event()
        self._lost_ev = asyncio.Event()
        self.poller.on_event(self.feed)
        try:
            if poll:
                await self.poller.start()
        except BaseException:
            await flusher.stop()
            ob.close()
            self._outbox = None
            raise

    def feed(self, ev: object) -> None:
        """A poller event (each output defines it)."""
        raise NotImplementedError

    async def _cancel_tasks(self) -> None:
        """Cancel the background tasks and wait for them; one that ended with an
        exception (`_supervise` reports their failures: a bug) is logged."""
        tasks, self._tasks = self._tasks, []
        for t in tasks:
            t.cancel()
        outcomes = await asyncio.gather(*tasks, return_exceptions=True)
        for t, outcome in zip(tasks, outcomes, strict=True):
            if isinstance(outcome, Exception):
                log.error("%s: task %s ended with %r", self.WHAT, t.get_name(), outcome)

    async def _close_outbox(self, closing: Callable[[], None] | None = None) -> None:
        """The flusher's last batch, its thread joined, ``closing()`` (the outbox's
        last figures), then the outbox closed."""
        ob, flusher = self._outbox, self._flusher
        assert ob is not None and flusher is not None
        await flusher.stop()
        if closing is not None:
            closing()
        ob.close()
        self._outbox = None

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

    def _halt(self, error: BaseException) -> None:
        """The output cannot go on: ``fatal`` says why, `halted` is set."""
        self.fatal = error
        if self._stop is not None:
            self._stop.set()

    # ------------------------------------------------------------------ updates

    def publish_value(self, point: Point, value: Value | None, read_at: float) -> None:
        """Publish a value read now (a write's read-back) whatever its deadband,
        unless it is the value last published (a poll may have read it first)."""
        if self.reporter.update(point, value, read_at, time.monotonic(), exact=True):
            self._append(point, value, read_at, "bad" if value is None else "good")

    def _append(
        self, point: Point, value: Value | None, read_at: float | None, quality: str
    ) -> None:
        """A point's value to publish: appended to the outbox as a point update (the
        flusher told), then handed to `_stored`; nothing when the outbox is closed,
        `_store_refused` when it refuses it."""
        ob = self._outbox
        if ob is None:
            return
        update = PointUpdate(point.name, value, read_at, quality)
        rec = encode_update(update)
        try:
            seq = ob.append(rec, time.monotonic())
        except (OutboxError, ValueError) as e:
            self._store_refused(e)
            return
        if self._flusher is not None:
            self._flusher.poke()
        self._stored(seq, rec, update)

    # ------------------------------------------------------------------ tasks

    def _on_lost(self, reason: str) -> None:
        """The output's connection ended (its task reconnects)."""
        if self._lost_ev is not None:
            self._lost_ev.set()

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
