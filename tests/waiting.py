"""Waiting for a state in a test: conditions are awaited, never timed."""

from __future__ import annotations

import asyncio
from collections.abc import Callable


async def wait_for(condition: Callable[[], bool], what: str, patience: float) -> None:
    """Until ``condition()`` holds (checked every 20 ms on the running loop); fail
    naming ``what`` after ``patience`` seconds (a safety net, not a measurement)."""
    loop = asyncio.get_running_loop()
    give_up = loop.time() + patience
    while not condition():
        assert loop.time() < give_up, f"gave up waiting for {what}"
        await asyncio.sleep(0.02)


#: A master's timeout where a test expects an answer: it only bounds how long a failure
#: takes, so it is generous (a loaded CI machine can stall a process for a few hundred
#: milliseconds).  A test about a timeout sets its own, with bounds in protocol times.
ANSWER_TIMEOUT = 2.0

#: The same where the test also expects silences (each costs this long): still several
#: hundred milliseconds above the longest stall seen on a loaded CI machine.
SILENCE_TIMEOUT = 1.0
