"""Stopping a command on SIGINT/SIGTERM, and when the reader of its stdout goes away
(re-exported by `pyrtu.cli.common`)."""

from __future__ import annotations

import asyncio
import io
import os
import select
import signal
import stat
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

__all__ = ["SignalStop", "stop_on_signals", "stop_when_stdout_closes"]


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
    done = threading.Event()
    watcher = threading.Thread(
        target=_watch_stdout, args=(stop, done), name="pyrtu-stdout-watch", daemon=True
    )
    watcher.start()
    try:
        yield stop
    finally:
        done.set()
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _watch_stdout(stop: threading.Event, done: threading.Event) -> None:
    """Set `stop` when stdout is a pipe whose reader closed (``| head -1``): a command
    that writes nothing more would otherwise run on for ever.  The pipe's write end
    then reports an error (POLLERR), seen without writing."""
    fd = _stdout_pipe()
    if fd is None:
        return
    poller = select.poll()
    poller.register(fd, select.POLLERR)
    while not done.is_set() and not stop.is_set():
        if poller.poll(200):
            stop.set()
            return


def _stdout_pipe() -> int | None:
    """stdout's descriptor when it is a pipe, else None."""
    try:
        fd = sys.stdout.fileno()
        return fd if stat.S_ISFIFO(os.fstat(fd).st_mode) else None
    except (OSError, ValueError, io.UnsupportedOperation):
        return None  # not a real pipe: a failing write tells


def stop_when_stdout_closes(
    loop: asyncio.AbstractEventLoop, stop: asyncio.Event
) -> Callable[[], None]:
    """The asyncio form of the watch above: set `stop` when stdout is a pipe whose
    reader closed (its write end reports an error, which the selector sees as
    readable).  Returns the function that takes the watch off the loop."""
    fd = _stdout_pipe()
    if fd is None:
        return lambda: None

    def hangup() -> None:
        loop.remove_reader(fd)
        stop.set()

    def unwatch() -> None:
        loop.remove_reader(fd)

    loop.add_reader(fd, hangup)
    return unwatch
