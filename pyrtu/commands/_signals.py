"""Stopping a command on SIGINT/SIGTERM (re-exported by `pyrtu.commands.common`)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

__all__ = ["SignalStop", "stop_on_signals"]


class SignalStop(BaseException):
    """Raised by `stop_on_signals(interrupt=True)`'s handler: SIGINT or SIGTERM came
    while the command may be blocked in a system call (a BaseException, so that no
    ``except Exception`` on the way swallows it)."""


@contextmanager
def stop_on_signals(interrupt: bool = False) -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs (handlers restored after).

    ``interrupt=True``: the handler also raises `SignalStop`, for a command that may
    block in a system call Python restarts after a signal (PEP 475), such as opening
    a FIFO that has no writer yet or reading one whose writer is silent; the
    command catches it and ends as on any stop."""
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()
        if interrupt:
            raise SignalStop(signal.Signals(signum).name)

    old: dict[signal.Signals, Any] = {}
    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, on_signal)
    try:
        yield stop
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
