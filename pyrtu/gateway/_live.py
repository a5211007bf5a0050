"""Which connections the gateway closes for not talking (sans-I/O; time is an input).

A TCP client holds one of ``max_connections`` slots for as long as its connection
is open, so a client that connects and sends nothing, or a request one byte at a
time, or half a header, could hold every slot.  Three rules free them:

* header timeout: a request begun (its first byte read) must be complete within
  ``header_timeout`` seconds (an MBAP ADU is at most 260 bytes: one segment on any
  network; a client dripping bytes is not sending a request);
* idle timeout: a connection with no complete request for ``idle_timeout`` seconds,
  and nothing of its waiting (queued, on a bus, or answers unsent), is closed;
* eviction: when the table is full, a newcomer takes the slot of the connection
  that has done least for it: one that never completed a request (the oldest of
  those first), else the longest idle one with nothing waiting.  Connections with
  work in progress are never evicted; when every slot has work, the newcomer is
  refused.

mbusd (``-T``, 60 s by default) closes a connection whose state has not changed for
that long and refuses newcomers when full; evicting instead means a full table of
silent clients can no longer lock out a client that talks.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

HEADER = "header"
IDLE = "idle"


@dataclass(slots=True)
class Liveness:
    """What the gateway knows of one connection's talking (monotonic seconds)."""

    connected: float
    #: when the request being received began (its first byte), None between requests
    partial_since: float | None = None
    #: when it last completed a request or was last answered, None before any
    last_active: float | None = None
    #: requests of its queued or on a bus (answers not yet written)
    outstanding: int = 0

    def data(self, now: float, partial: bool, completed: bool) -> None:
        """Bytes were read at ``now``: ``completed`` if they ended at least one
        request, ``partial`` if bytes of an unfinished request remain buffered."""
        if completed:
            self.last_active = now
            self.partial_since = now if partial else None
        elif partial and self.partial_since is None:
            self.partial_since = now

    def answered(self, now: float) -> None:
        self.outstanding -= 1
        self.last_active = now

    def idle_since(self) -> float:
        return self.connected if self.last_active is None else self.last_active

    def expired(self, now: float, header_timeout: float, idle_timeout: float) -> str | None:
        """`HEADER` or `IDLE` when the connection must be closed at ``now`` (a
        timeout of 0 is no limit), else None."""
        since = self.partial_since
        if header_timeout and since is not None and now - since >= header_timeout:
            return HEADER
        if (
            idle_timeout
            and self.outstanding <= 0
            and since is None
            and now - self.idle_since() >= idle_timeout
        ):
            return IDLE
        return None


def pick_victim(
    candidates: Iterable[tuple[int, Liveness, bool]],
) -> int | None:
    """The connection a newcomer replaces in a full table: of (id, liveness, busy)
    with ``busy`` when answers to it wait unsent, the oldest that never completed a
    request, else the longest idle; never one with work in progress.  None: refuse."""
    best: tuple[int, float, int] | None = None  # (rank, since, id): lowest wins
    for conn_id, live, busy in candidates:
        if busy or live.outstanding > 0:
            continue
        key = (
            (0, live.connected, conn_id)
            if live.last_active is None
            else (1, live.last_active, conn_id)
        )
        if best is None or key < best:
            best = key
    return None if best is None else best[2]
