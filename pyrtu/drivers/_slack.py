"""Timer slack of the threads that keep a line's timing (Linux only; a leaf module).

Linux wakes a sleeping thread up to its *timer slack* (50 µs by default) after the
time it asked for, to batch wake-ups.  At 115200 baud t3.5 is 1750 µs and a
character 87-95 µs, so that slack is a visible share of every silence a master or
a slave keeps.  The drivers shrink the slack of the thread that runs their
transactions to 1 µs, once per thread (``prctl(PR_SET_TIMERSLACK)``; the setting
belongs to the thread and only makes its timed waits more exact).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import threading

__all__ = ["set_timer_slack", "swap_timer_slack", "tighten_this_thread"]

_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30
_libc: ctypes.CDLL | None = None
if sys.platform.startswith("linux"):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    except OSError:  # pragma: no cover - no libc to load
        _libc = None

_tight = threading.local()


def set_timer_slack(ns: int = 1000) -> bool:
    """Set this thread's timer slack to ``ns`` nanoseconds; False where unsupported."""
    if _libc is None:
        return False
    try:
        return int(_libc.prctl(_PR_SET_TIMERSLACK, ns, 0, 0, 0)) == 0
    except AttributeError:  # pragma: no cover - no prctl
        return False


def swap_timer_slack(ns: int | None) -> int | None:
    """Set this thread's timer slack to ``ns`` nanoseconds (None: leave it); the old
    slack, to restore later, or None where unsupported."""
    if _libc is None:
        return None
    try:
        old = int(_libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))
    except AttributeError:  # pragma: no cover - no prctl
        return None
    if old < 0:
        return None
    if ns is not None:
        _libc.prctl(_PR_SET_TIMERSLACK, ns, 0, 0, 0)
    return old


def tighten_this_thread() -> None:
    """1 µs of timer slack for the calling thread, the first time it asks."""
    if not getattr(_tight, "done", False):
        _tight.done = True
        set_timer_slack(1000)
