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
