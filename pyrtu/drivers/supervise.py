"""Supervised background tasks: one rule for every long-running command.

A task that raises is never swallowed: `supervise` runs its body as an asyncio
task; when the body raises, the failure goes to ``report`` (the subsystem logs it
once with its cause, emits its event and counts it), ``cleanup`` puts things
right, and the body starts again after the shared back-off of
`pyrtu.drivers.reconnect`.  A run of failures is one outage: ``report`` is told
which failure is the ``first`` (report it: a log line, an event) and which are
the next (count them, debug level); a body that ran ``maximum`` seconds before it
failed again begins a new run.  Used by the bridge, the poller's bus tasks, the
gateway's bus workers and sweeper, and the ``--metrics`` HTTP server.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from .reconnect import Backoff, Reconnect


def cause(error: BaseException) -> str:
    """A failure for people: ``"Type: message"`` (the type alone when it has none)."""
    return f"{type(error).__name__}: {error}" if str(error) else type(error).__name__


@dataclass(frozen=True)
class TaskFailure:
    """A supervised task raised: ``task`` its name, ``error`` the exception,
    ``retry_in`` the seconds until it starts again, ``first`` whether this begins a
    run of failures (report it) or continues one (count it)."""

    task: str
    error: BaseException
    retry_in: float
    first: bool

    @property
    def cause(self) -> str:
        return cause(self.error)


def supervise(
    name: str,
    body: Callable[[], Awaitable[None]],
    report: Callable[[TaskFailure], None],
    *,
    backoff: Backoff,
    running: Callable[[], bool],
    cleanup: Callable[[], None] | None = None,
) -> asyncio.Task[None]:
    """Run ``body()`` as the task ``name`` while ``running()``; when it raises an
    ``Exception``, call ``report`` then ``cleanup`` and start it again after the
    back-off.  The task ends when ``body`` returns, when ``running()`` is false
    after a failure, or when it is cancelled."""
    retry = Reconnect(backoff)

    async def supervised() -> None:
        while running():
            began = time.monotonic()
            try:
                await body()
                return
            except Exception as error:
                now = time.monotonic()
                if now - began >= retry.backoff.maximum:
                    retry.recovered(now)  # it had run well: a new run of failures
                first = retry.failed(now, error)
                wait = retry.wait(now)
                report(TaskFailure(name, error, wait, first))
                if cleanup is not None:
                    cleanup()
                await asyncio.sleep(wait)

    return asyncio.create_task(supervised(), name=name)


__all__ = ["TaskFailure", "cause", "supervise"]
