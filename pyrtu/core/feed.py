"""The one "feed until taken" loop over a framer core (RTU, ASCII or MBAP).

A core's ``feed`` may take fewer bytes than it is given: a silence before them
ends the frame in progress first, or a frame ends inside them and the core stops
there so that its event can be taken before the next frame begins.  The caller
then takes the events and feeds the rest.  A core that takes nothing three times
running, its events taken in between, is broken: that is an internal error, not
something the bytes can cause.

``feed`` is the core's feed with its other arguments bound (the RTU and ASCII
cores take the time: ``lambda chunk: core.feed(chunk, now_us)``; the MBAP core
takes the bytes alone); ``drain`` takes the events the core has and returns True
to stop early (a client that has its answer leaves the rest unread), anything
false to go on.
"""

from __future__ import annotations

from collections.abc import Callable

#: feeds in a row that took no byte before the core is deemed stuck
_STALL_LIMIT = 2


def feed_all(feed: Callable[[bytes], int], data: bytes, drain: Callable[[], object]) -> int:
    """Feed ``data`` to a core until it has taken all of it (or ``drain`` says stop),
    calling ``drain()`` after every feed; returns the bytes taken.  RuntimeError when
    the core takes nothing more than twice in a row."""
    size = len(data)
    took = feed(data)
    stop = drain()
    if took == size:  # the common case: one feed
        return size
    pos = took
    stalled = 0 if took else 1
    while pos < size and not stop:
        took = feed(data[pos:])
        stop = drain()
        pos += took
        if took:
            stalled = 0
        else:
            stalled += 1
            if stalled > _STALL_LIMIT:
                raise RuntimeError("framer made no progress (internal error)")
    return pos


__all__ = ["feed_all"]
