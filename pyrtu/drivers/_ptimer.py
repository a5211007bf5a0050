"""Timers to the microsecond on any asyncio event loop.

asyncio's default loop waits in epoll, whose timeout is whole milliseconds: every
``call_at`` fires up to a millisecond late, a large part of t3.5 (1.75 ms) at 115200
baud.  uvloop's timers are milliseconds too.  A library cannot choose its host's loop,
so the drivers schedule their timed wake-ups here instead:

* on a loop that already waits to the microsecond (`pyrtu.drivers.aio.new_event_loop`'s
  select() loop, marked by `mark_precise`), `call_at` is the loop's own;
* elsewhere on Linux, one timerfd per loop (CLOCK_MONOTONIC, the clock of
  ``time.monotonic()`` and of asyncio's ``loop.time()``) armed at the earliest
  deadline with an absolute time, watched with ``add_reader``: the loop's selector
  wakes when the kernel's timer fires, whatever its own timeout resolution;
* without timerfd (not Linux), the loop's own ``call_at``.

Deadlines are ``time.monotonic()`` seconds, as the protocols give them.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import heapq
import itertools
import os
import time
import weakref
from collections.abc import Callable
from typing import Any

from pyrtu.drivers import _slack

_CLOCK_MONOTONIC = 1
_TFD_NONBLOCK = 0o4000
_TFD_CLOEXEC = 0o2000000
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _bind_timerfd(libc: Any) -> Any:
    """The C library with timerfd_create/timerfd_settime typed, or None (not Linux)."""
    if libc is None:
        return None
    try:
        libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.timerfd_create.restype = ctypes.c_int
        libc.timerfd_settime.argtypes = [
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_Itimerspec),
            ctypes.POINTER(_Itimerspec),
        ]
        libc.timerfd_settime.restype = ctypes.c_int
    except AttributeError:
        return None
    return libc


_libc = _bind_timerfd(_slack._libc)  # the one C library handle (pyrtu.drivers._slack loads it)
_PRECISE_ATTR = "_pyrtu_precise_timers"


def mark_precise(loop: asyncio.AbstractEventLoop) -> None:
    """Say that `loop`'s own timers are exact (a select() loop): no timerfd needed."""
    setattr(loop, _PRECISE_ATTR, True)


class TimerHandle:
    """What `call_at` returns: `cancel()` it, as asyncio's own handle."""

    __slots__ = ("_args", "_callback", "cancelled", "when")

    def __init__(self, when: float, callback: Callable[..., object], args: tuple[Any, ...]):
        self.when = when
        self._callback = callback
        self._args = args
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class _TimerFd:
    """One loop's timerfd and the heap of its deadlines."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        fd = _libc.timerfd_create(_CLOCK_MONOTONIC, _TFD_NONBLOCK | _TFD_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
        self.fd = fd
        _slack.tighten_this_thread()  # the loop's thread: 1 us of slack on its waits
        self._heap: list[tuple[float, int, TimerHandle]] = []
        self._seq = itertools.count()
        self._armed: float | None = None
        self._spec = _Itimerspec()
        try:
            loop.add_reader(fd, self._fire)
        except BaseException:
            os.close(fd)
            raise
        # the descriptor goes with the loop: closed by loop.close() (wrapped here),
        # or when the loop is collected if its close cannot be wrapped.  Nothing
        # here refers to the loop, so the weak mapping below can let it go.
        closer = weakref.finalize(loop, os.close, fd)
        close = loop.close

        def close_too() -> None:
            try:
                close()
            finally:
                _timers.pop(loop, None)
                closer()

        with contextlib.suppress(AttributeError, TypeError):
            loop.close = close_too  # type: ignore[method-assign]

    def add(self, handle: TimerHandle) -> None:
        heapq.heappush(self._heap, (handle.when, next(self._seq), handle))
        if self._armed is None or handle.when < self._armed:
            self._arm(handle.when)

    def _arm(self, when: float) -> None:
        # an absolute CLOCK_MONOTONIC time; 0 would disarm, so a past deadline is 1 ns
        ns = max(1, int(when * 1e9))
        spec = self._spec
        spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(ns, 1_000_000_000)
        if _libc.timerfd_settime(self.fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")
        self._armed = when

    def _fire(self) -> None:
        try:
            os.read(self.fd, 8)
        except BlockingIOError:
            pass  # woken by a re-arm that came after the expiry was read
        self._armed = None
        heap = self._heap
        now = time.monotonic()
        while heap and (heap[0][2].cancelled or heap[0][0] <= now):
            _, _, h = heapq.heappop(heap)
            if not h.cancelled:
                h.cancelled = True
                h._callback(*h._args)
        while heap and heap[0][2].cancelled:
            heapq.heappop(heap)
        if heap:
            self._arm(heap[0][0])


_timers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, _TimerFd] = (
    weakref.WeakKeyDictionary()
)


def _timerfd(loop: asyncio.AbstractEventLoop) -> _TimerFd | None:
    if _libc is None or getattr(loop, _PRECISE_ATTR, False):
        return None
    t = _timers.get(loop)
    if t is None:
        try:
            t = _timers[loop] = _TimerFd(loop)
        except (OSError, NotImplementedError):  # no timerfd, or a loop without add_reader
            setattr(loop, _PRECISE_ATTR, True)  # use its own timers from now on
            return None
    return t


def call_at(
    loop: asyncio.AbstractEventLoop, when: float, callback: Callable[..., object], *args: Any
) -> TimerHandle | asyncio.TimerHandle:
    """``loop.call_at`` to the microsecond: `when` is a ``time.monotonic()`` time."""
    t = _timerfd(loop)
    if t is None:
        return loop.call_at(when, callback, *args)
    h = TimerHandle(when, callback, args)
    t.add(h)
    return h


def rearm(
    old: asyncio.TimerHandle | None, when: float | None, callback: Callable[[], object]
) -> asyncio.TimerHandle | None:
    """Cancel ``old`` and schedule ``callback`` at ``when`` (a ``time.monotonic()``
    time; None: no timer) on the running loop's own timers (millisecond work:
    connection and framer timeouts); the new handle."""
    if old is not None:
        old.cancel()
    if when is None:
        return None
    loop = asyncio.get_running_loop()
    return loop.call_at(loop.time() + max(0.0, when - time.monotonic()), callback)


async def sleep_until(when: float) -> None:
    """Sleep until ``time.monotonic()`` reaches `when`, to the microsecond."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[None] = loop.create_future()
    h = call_at(loop, when, _set_none, fut)
    try:
        await fut
    finally:
        h.cancel()


def _set_none(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
