"""The hub thread of `VirtualBus`: the C loop and the Python loop.

The C loop (`HubLoops._c_loop`) runs csrc/rtu_vbus_io.c (the schedule and the pty
I/O in C; a cffi call releases the GIL) and comes back to Python only for inotify
events, unplugs and stop requests.  The Python loop (`HubLoops._loop`) runs the twin
schedule (pyrtu/core/_pure/vbus.py) in a select() loop: the pure backend, a capture,
or seeded line faults.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import select
import termios
import threading
import time
from collections.abc import Callable

from pyrtu.core._pure.vbus import Schedule

from ._cvbus import CLoop, CSchedule
from ._os import OpenWatch, set_realtime, set_timer_slack
from ._state import DropState

__all__ = ["DEFAULT_LATENCY", "HubLoops"]

_ns = time.perf_counter_ns
#: Wake this long before a delivery and spin the rest: select() wakes late by tens
#: of microseconds, a few with real-time priority.
_SPIN_NS = 50_000
_SPIN_RT_NS = 20_000
_READ_SIZE = 4096
#: Wake at least this often when idle: a thread that sleeps longer wakes slower
#: (CPU idle states, VM halts), which delays noticing a client's write.
_IDLE_TICK = 0.002
#: ... for this long after the last activity (and after start).
_WARM_NS = 2_000_000_000
#: Compensated pseudo-terminal latencies (s): client write -> hub read, and hub
#: write -> client read (typical medians measured on Linux VMs; see docs/vbus.md).
DEFAULT_LATENCY = (70e-6, 40e-6)


def _wait_readable(fds: list[int], timeout: float | None) -> list[int]:
    """select() with microsecond timeouts; poll() when an fd is beyond FD_SETSIZE."""
    try:
        if max(fds) < 1024:
            return select.select(fds, [], [], timeout)[0]
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        ms = None if timeout is None else math.ceil(timeout * 1000)
        return [fd for fd, _ in poller.poll(ms)]
    except (OSError, ValueError):
        return []  # an fd closed under us (shutdown); the loop re-reads the state


class HubLoops:
    """The hub thread's loops (a base of `VirtualBus`, which sets these attributes)."""

    _drops: list[DropState]
    _sched: Schedule | CSchedule
    _cloop: CLoop | None
    _lock: threading.RLock
    _stop: bool
    _to_python: bool
    _watch: OpenWatch | None
    _wake_r: int
    _anchor_ns: int
    _lead_ns: int
    _want_realtime: bool
    _spin_ns: int
    char_ns: int
    t0_ns: int
    realtime: bool
    loop: str
    error: BaseException | None

    _locked: Callable[[], contextlib.AbstractContextManager[Schedule | CSchedule]]
    _unplug_now: Callable[[DropState], None]

    def _take_over(self) -> None:
        """(Lock held, the C loop not running.)  The twin takes the C schedule's state."""
        old, cloop = self._sched, self._cloop
        if not isinstance(old, CSchedule) or cloop is None:
            return
        new = Schedule(len(self._drops), self.char_ns, self._lead_ns)
        for i, d in enumerate(new.drops):
            c = old.drops[i]
            d.q.extend(old.queued(i))
            d.tx_free, d.rx_end = int(c.tx_free), int(c.rx_end)
            d.last = (int(c.last_start), int(c.last_byte)) if c.has_last else None
            d.alive, d.cut, d.echo = bool(c.alive), bool(c.cut), bool(c.echo)
            d.unplug_left = int(c.unplug_left)
            d.event_at = None if c.event_at == -(2**63) else int(c.event_at)
            d.batch_ns, d.batch_bytes = int(c.batch_ns), int(c.batch_bytes)
            d.hold = bytearray(old.held(i))
            d.hold_deadline = None if c.hold_deadline == -(2**63) else int(c.hold_deadline)
            d.hold_end, d.episode = int(c.hold_end), int(c.episode)
            d.out = bytearray(old.take_output(i))
            d.counters = old.drop_counters(i)
            d.tx = self._drops[i].tx
        new.wire_bytes, new.collisions, new.collided = old.wire_bytes, old.collisions, old.collided
        new._coll_until = int(old.s.coll_until)
        new.t0_ns = self.t0_ns
        self._sched = new
        self._cloop = None
        cloop.destroy()
        self.loop = "python"

    def _run(self) -> None:
        set_timer_slack(1000)
        if self._want_realtime:
            self.realtime = set_realtime(1)
        self._spin_ns = _SPIN_RT_NS if self.realtime else _SPIN_NS
        try:
            if self._cloop is not None:
                self._c_loop()
            self._loop()
        except BaseException as exc:  # pragma: no cover - reported to the owner
            self.error = exc
            raise

    def _c_loop(self) -> None:
        """Run the C I/O loop; come back to Python for what only Python does."""
        while not self._stop:
            cloop = self._cloop
            if cloop is None:
                return
            reason = cloop.run()  # the GIL is released for as long as it runs
            with self._lock:
                if reason == cloop.UNPLUG:
                    cloop.lock()
                    try:
                        due = cloop.sched.take_due()
                    finally:
                        cloop.unlock()
                    for i in due:
                        self._unplug_now(self._drops[i])
                elif reason == cloop.WATCH:
                    self._watch_events()
                elif reason == cloop.ERRNO:
                    code = cloop.errno()
                    raise OSError(code, f"virtual bus I/O loop: {os.strerror(code)}")
                elif reason != cloop.STOPPED:
                    raise RuntimeError(f"rtu_vbus_io_run failed with status {reason}")
                if self._to_python:
                    self._take_over()
                    self._to_python = False
                    return

    def _loop(self) -> None:
        active_until = _ns() + _WARM_NS
        while not self._stop:
            now = _ns()
            with self._lock:
                sched = self._sched
                for i in sched.service(now):
                    self._unplug_now(self._drops[i])
                self._flush(sched)
                deadline = sched.deadline()
                rfds = [
                    d.pty.master
                    for d in self._drops
                    if d.pty is not None and sched.space(d.index) > 0
                ]
                watch_fd = self._watch.fd if self._watch is not None else -1
            rfds.append(self._wake_r)
            if watch_fd >= 0:
                rfds.append(watch_fd)
            wait: float | None = None
            if deadline is not None:
                remaining = deadline - _ns()
                if remaining <= self._spin_ns:
                    self._spin(deadline)
                    continue
                wait = (remaining - self._spin_ns) / 1e9
            if now < active_until and (wait is None or wait > _IDLE_TICK):
                wait = _IDLE_TICK
            ready = _wait_readable(rfds, wait)
            if ready:
                active_until = _ns() + _WARM_NS
                self._on_ready(ready, watch_fd)

    def _flush(self, sched: Schedule | CSchedule) -> None:
        """Write what each drop receives (Python loop)."""
        for d in self._drops:
            data = sched.take_output(d.index)
            if not data:
                continue
            if d.pty is None or not d.heard:
                sched.written(d.index, 0, -1 if d.pty is None else 0)
                continue
            try:
                n = os.write(d.pty.master, data)
            except OSError:  # BlockingIOError (the pty is full) included
                n = 0
            sched.written(d.index, n, 1)

    def _spin(self, deadline: int) -> None:
        # Brief busy-wait for the last stretch; sleep(0) lets other threads run.
        while _ns() < deadline:
            time.sleep(0)

    def _on_ready(self, ready: list[int], watch_fd: int) -> None:
        with self._lock:
            if watch_fd in ready:
                self._watch_events()
            if self._wake_r in ready:
                try:
                    os.read(self._wake_r, 4096)
                except OSError:
                    pass
            sched = self._sched
            for d in self._drops:
                if d.pty is None or d.pty.master not in ready:
                    continue
                space = min(_READ_SIZE, sched.space(d.index))
                if space <= 0:
                    continue
                try:
                    data = os.read(d.pty.master, space)
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EIO, errno.EINTR):
                        continue
                    raise
                if data:
                    sched.transmit(d.index, data, _ns() - self._anchor_ns)

    def _watch_events(self) -> None:
        if self._watch is None:
            return
        for key, delta in self._watch.read():
            self._client_event(self._drops[key], delta)

    def _client_event(self, d: DropState, delta: int) -> None:
        before = d.clients
        d.clients = max(0, d.clients + delta)
        if (before == 0) != (d.clients == 0) and d.pty is not None:
            # first client arrived or last one left: nothing stale stays queued
            try:
                termios.tcflush(d.pty.slave, termios.TCIFLUSH)
            except termios.error:
                pass
            with self._locked() as sched:
                sched.clear_hold(d.index)
                if self._cloop is not None:
                    self._cloop.set_heard(d.index, d.heard)
