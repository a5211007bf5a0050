"""Helpers of the tests of a master's reopen and reconnect (`pyrtu.drivers.links.LinkRevival`)."""

from __future__ import annotations

from pyrtu.drivers.reconnect import Backoff, Reconnect


def schedule(link: object, initial: float) -> Reconnect:
    """The master's retry schedule, set to ``initial`` seconds between attempts."""
    reconnect = Reconnect(Backoff(initial=initial, maximum=initial, jitter=0.0))
    link._revive.reconnect = reconnect  # type: ignore[attr-defined]
    return reconnect
