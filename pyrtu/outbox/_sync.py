"""The outbox's fsync batches off the event loop (outbox.py, bridge.py).

A flush has three parts: `Outbox.begin_flush` on the driver's thread writes the
buffered bytes and hands what needs an fsync to a `Batch`; `Batch.run` does the
fdatasyncs (segments, directory, cursor) on any thread; `Outbox.end_flush` back
on the driver's thread makes the batch's records durable (`pending` returns them)
or raises its error.  `Flusher` runs the middle part on one dedicated thread, one
batch at a time, so the loop never waits for the disk.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from pyrtu.outbox import _format as fmt
from pyrtu.outbox._parts import RESERVE, OutboxError, OutboxLimits, Segment, io_error


@dataclass(eq=False)
class Batch:
    """What one flush makes durable.  The batch owns its file descriptors: the
    sealed segments' (closed once synced, given back on an error) and duplicates
    of the active segment's and the directory's (always closed)."""

    directory: Path
    target: int  # every record up to this seq is durable once the batch is done
    records: int  # records appended since the last flush (given back on an error)
    since: float | None  # when the oldest of them was appended
    sealed: list[tuple[Segment, int]] = field(default_factory=list)
    active: int = -1
    dir_fd: int = -1
    #: the cursor to save (acks, drops; ``reserve``: numbers reserved ahead)
    save: Callable[[int | None], None] | None = None
    reserve: int | None = None
    error: OutboxError | None = None

    def run(self) -> None:
        """fdatasync the segments, fsync the directory, save the cursor; an error is
        kept in ``error`` (raised by `Outbox.end_flush`)."""
        what = "a segment"
        try:
            for _seg, fd in self.sealed:
                os.fdatasync(fd)
            if self.active >= 0:
                os.fdatasync(self.active)
            what = "the directory"
            if self.dir_fd >= 0:
                os.fsync(self.dir_fd)
            if self.save is not None:
                self.save(self.reserve)
        except OutboxError as exc:
            self.error = exc
        except OSError as exc:
            self.error = io_error(self.directory, "fsyncing", what, exc)
        finally:
            fds = [self.active, self.dir_fd]
            if self.error is None:
                fds += [fd for _seg, fd in self.sealed]
                self.sealed = []
            self.active = self.dir_fd = -1
            for fd in fds:
                if fd >= 0:
                    os.close(fd)


class Flusher:
    """The outbox's fsync batches on one dedicated thread, one batch at a time.

    `poke` (after an append or an ack) arms a timer for the outbox's `flush_at`;
    then `begin_flush` runs on the loop (the buffered bytes written), the batch's
    fsyncs on the thread, and ``done(error)`` back on the loop once `end_flush`
    made its records durable (error: the `OutboxError` of a failed batch, whose
    records are flushed again next time).  `stop` flushes what is left and joins
    the thread.
    """

    def __init__(self, outbox: Flushing, done: Callable[[OutboxError | None], None]) -> None:
        self._outbox = outbox
        self._done = done
        self._queue: queue.SimpleQueue[Batch | None] = queue.SimpleQueue()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._idle: asyncio.Event | None = None
        self._timer: asyncio.TimerHandle | None = None
        self.busy = False
        self.batches = 0  # batches done

    def start(self) -> None:
        """Start the thread (in the running loop, which gets the results)."""
        self._loop = asyncio.get_running_loop()
        self._idle = asyncio.Event()
        self._idle.set()
        self._thread = threading.Thread(target=self._work, name="pyrtu-outbox-fsync", daemon=True)
        self._thread.start()

    def poke(self) -> None:
        """Something to flush may be there: arm the timer for it (if not armed, and
        no batch is in flight: its end pokes again)."""
        if self._timer is not None or self.busy or self._loop is None:
            return
        at = self._outbox.flush_at
        if at is not None:
            delay = max(0.0, at - time.monotonic())
            self._timer = self._loop.call_later(delay, self._tick)

    def _tick(self) -> None:
        self._timer = None
        if self._outbox.flush_due(time.monotonic()):
            self.submit()
        self.poke()

    def submit(self) -> bool:
        """Write the buffered bytes and hand the batch to the thread; False when a
        batch is in flight, the thread is not running, or the write failed (disk
        full: ``done(error)``, tried again after ``fsync_interval``)."""
        if self.busy or self._thread is None or self._idle is None or self._outbox.closed:
            return False
        try:
            batch = self._outbox.begin_flush()
        except OutboxError as e:
            self._done(e)
            self._retry()
            return False
        self.busy = True
        self._idle.clear()
        self._queue.put(batch)
        return True

    def _work(self) -> None:
        loop = self._loop
        assert loop is not None
        while (batch := self._queue.get()) is not None:
            batch.run()
            try:
                loop.call_soon_threadsafe(self._finished, batch)
            except RuntimeError:  # the loop is closed: nobody waits for the result
                return

    def _finished(self, batch: Batch) -> None:
        self.busy = False
        self.batches += 1
        if self._idle is not None:
            self._idle.set()
        if self._outbox.closed:
            for _seg, fd in batch.sealed:
                with contextlib.suppress(OSError):
                    os.close(fd)
            return
        try:
            self._outbox.end_flush(batch)
        except OutboxError as e:
            self._done(e)
            self._retry()
        else:
            self._done(None)
            self.poke()

    def _retry(self) -> None:
        """After a failure: the next attempt after ``fsync_interval`` (at least 10
        ms), not at once (a failing disk must not spin the loop)."""
        if self._loop is not None and self._timer is None:
            wait = max(0.01, self._outbox.limits.fsync_interval)
            self._timer = self._loop.call_later(wait, self._tick)

    async def wait(self) -> None:
        """Until no batch is in flight."""
        if self._idle is not None:
            await self._idle.wait()

    async def stop(self) -> None:
        """Wait for the batch in flight, flush the rest the same way, end the thread
        and join it."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        await self.wait()
        if self.submit():
            await self.wait()
        if self._timer is not None:  # (re-armed by a failed write or the last batch)
            self._timer.cancel()
            self._timer = None
        thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            thread.join()


class Flushing:
    """The flushing part of `Outbox` (its base: the state is the outbox's)."""

    directory: Path
    limits: OutboxLimits
    _closed: bool
    _segs: list[Segment]
    _unsynced: list[tuple[Segment, int]]
    _buf: bytearray
    _fd: int
    _dir_fd: int
    _state_fd: int
    _dir_dirty: bool
    _state_lock: threading.Lock
    _next_seq: int
    _durable_seq: int
    _acked: int
    _dropped: int
    _reserved: int
    _gen: int
    _saved: tuple[int, int, int]
    _unflushed: int
    _unflushed_since: float | None
    _dirty_since: float | None
    _write_out: Callable[[], None]

    @property
    def closed(self) -> bool:
        return self._closed

    def flush(self) -> None:
        """Write and fsync everything appended so far, and the ack cursor, on this
        thread (`begin_flush`, `Batch.run`, `end_flush`)."""
        batch = self.begin_flush()
        batch.run()
        self.end_flush(batch)

    def begin_flush(self) -> Batch:
        """A flush's first part, on the driver's thread: write the buffered bytes and
        hand what needs an fsync to a `Batch`, whose `run` may go on another thread
        (one batch at a time); then `end_flush`.  Later appends go to the next batch."""
        if self._closed:
            raise ValueError("flush on a closed Outbox")
        batch = Batch(self.directory, self._next_seq - 1, self._unflushed, self._unflushed_since)
        if self._unflushed or self._buf or self._unsynced:
            self._write_out()  # OutboxError (disk full): nothing handed over
            batch.sealed, self._unsynced = self._unsynced, []
            if self._fd >= 0:
                batch.active = self._dup(self._fd, batch)
        if self._dir_dirty:
            batch.dir_fd = self._dup(self._dir_fd, batch)
            self._dir_dirty = False
        if self._reserved - self._next_seq < RESERVE // 2:  # ahead, off the driver's thread
            batch.reserve = self._next_seq + RESERVE
        if batch.reserve or self._saved != (self._acked, self._saved[1], self._dropped):
            batch.save = self._save_ahead
        self._unflushed = 0
        self._unflushed_since = self._dirty_since = None
        return batch

    def _dup(self, fd: int, batch: Batch) -> int:
        try:
            return os.dup(fd)
        except OSError as exc:
            self._unsynced = batch.sealed + self._unsynced
            batch.sealed = []
            batch.run()  # closes what it holds
            raise io_error(self.directory, "duplicating", "a file descriptor", exc) from exc

    def end_flush(self, batch: Batch) -> None:
        """A flush's last part, on the driver's thread: the batch's records are
        durable (`pending` returns them), or its `OutboxError` is raised and what it
        held is flushed again next time."""
        if batch.error is None:
            self._durable_seq = max(self._durable_seq, batch.target)
            return
        live = set(map(id, self._segs))
        for seg, fd in batch.sealed:
            if id(seg) not in live:
                os.close(fd)  # acked or dropped meanwhile
        self._unsynced = [e for e in batch.sealed if id(e[0]) in live] + self._unsynced
        batch.sealed = []
        self._dir_dirty = True
        self._unflushed += batch.records
        if self._unflushed_since is None:
            self._unflushed_since = batch.since
        raise batch.error

    def _sync_dir(self) -> None:
        if self._dir_dirty:
            try:
                os.fsync(self._dir_fd)
            except OSError as exc:
                raise io_error(self.directory, "fsyncing", "the directory", exc) from exc
            self._dir_dirty = False

    def _save_ahead(self, reserve: int | None) -> None:
        """A batch's cursor (any thread): the acks and drops, and ``reserve``
        numbers reserved ahead (never fewer than the driver's thread reserved)."""
        self._save_state(reserve, ahead=True)

    def _save_state(self, reserved: int | None = None, *, ahead: bool = False) -> None:
        with self._state_lock:  # a batch's thread and the driver's (reserve, drops)
            res = self._saved[1] if reserved is None else reserved
            if ahead:
                res = max(res, self._saved[1])
            state = fmt.CursorState(self._gen + 1, self._acked, res, self._dropped)
            off, data = fmt.encode_state(state)
            try:
                os.pwrite(self._state_fd, data, off)
                os.fdatasync(self._state_fd)
            except OSError as exc:
                raise io_error(self.directory, "writing", "cursor", exc) from exc
            self._gen = state.gen
            self._reserved = res
            self._saved = (self._acked, res, self._dropped)

    def flush_due(self, now: float) -> bool:
        """Whether the driver should call flush() now: fsync_records appends, or
        fsync_interval after the first unflushed append (or after this method first
        saw acks not yet on disk)."""
        if self._unflushed >= self.limits.fsync_records:
            return True
        if self._unflushed_since is not None:
            return now >= self._unflushed_since + self.limits.fsync_interval
        if (self._acked, self._dropped) != (self._saved[0], self._saved[2]):
            if self._dirty_since is None:
                self._dirty_since = now
            return now >= self._dirty_since + self.limits.fsync_interval
        return False

    @property
    def flush_at(self) -> float | None:
        """When flush() is due (None: nothing to flush); see flush_due()."""
        if self._unflushed_since is not None:
            if self._unflushed >= self.limits.fsync_records:
                return self._unflushed_since
            return self._unflushed_since + self.limits.fsync_interval
        if self._dirty_since is not None:
            return self._dirty_since + self.limits.fsync_interval
        return None


__all__ = ["Batch", "Flusher", "Flushing"]
