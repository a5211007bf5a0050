"""One master exchange on a serial descriptor: what the drivers hand the backend's
`Exchanger` and what it reports (csrc/rtu_xfer.h; the twin: pyrtu/core/_pure/xfer.py).

The client protocol decides every time and length (`pyrtu.protocol.client_actions.
Exchange`); an exchanger carries them out in one call: sleep to the send time, look
for stale input (then nothing is sent), write the request, sleep to the first read,
read the rest as it comes (all but the last character slept through), until the
answer's length (an exception answer's shorter one) or the deadline.  With nothing
awaited (``expect`` 0) it is a write at a time: a slave's response at the end of its
turnaround (`pyrtu.protocol.server.Reply` handed out ahead).  Times are monotonic
seconds (``time.monotonic``'s clock).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

#: how an exchange ended (`XferResult.status`)
ANSWER, STALE, SHORT, ERRNO, GONE, CANCELLED = range(6)
#: where an ERRNO exchange failed (`XferResult.stage`)
STAGE_WRITE, STAGE_READ = 1, 2
#: bytes an exchange reads at most (an answer is at most 256; the rest is noise)
CAPACITY = 4096


class XferResult(NamedTuple):
    """What an exchange saw.  ``status``: ANSWER (the expected bytes came; with none
    expected, the request went), STALE (input was pending at the send time: nothing
    sent, ``data`` holds it), SHORT (the deadline, or a signal, with fewer bytes),
    ERRNO (``err`` at ``stage``), GONE (the descriptor reported input but gave
    none), CANCELLED (`AsyncExchanger.cancel`).  ``sent``: the request was written,
    from ``start`` to ``end`` (its transmission's end); ``data[:first_n]`` came in
    the first read of the answer, at ``first_t``; ``last_t``: when the last read
    returned; ``reads``: the reads that returned bytes."""

    status: int
    sent: bool
    start: float
    end: float
    data: bytes
    first_n: int
    first_t: float
    last_t: float
    err: int
    stage: int
    reads: int


class Exchanger(Protocol):
    """A backend's exchange step (``backend.Exchanger()``: one per port).

    ``run(fd, drain, request, send_at, first_wake, timeout, char, expect, short_len,
    look=True)`` carries out one exchange on ``fd``: ``drain``: tcdrain after the
    write (a real line); ``first_wake``: seconds after the end of transmission;
    ``timeout``: the deadline, seconds after it; ``char``: one character's time;
    ``expect``: the answer's length (0: none awaited); ``short_len``: an exception
    answer's (0: none); ``look``: input pending at the send time is stale and nothing
    is sent (a master).  ValueError for arguments out of range."""

    def run(
        self,
        fd: int,
        drain: bool,
        request: bytes,
        send_at: float,
        first_wake: float,
        timeout: float,
        char: float,
        expect: int,
        short_len: int,
        look: bool = True,
    ) -> XferResult: ...


class AsyncExchanger(Protocol):
    """A backend's exchanges on a thread of their own, for an event loop
    (``backend.AsyncExchanger()``: one per port; C: csrc/rtu_xfer_io.c's worker).
    `submit` takes `Exchanger.run`'s arguments and returns at once (RuntimeError while
    an exchange is under way); the loop watches ``fd`` (readable once it is over) and
    calls `result` (the last exchange's report; None while one is under way);
    `cancel` ends the exchange under way (before its write if that is not due yet:
    the report still comes, status CANCELLED); `close` ends the thread, the exchange
    under way cancelled."""

    fd: int

    def submit(
        self,
        fd: int,
        drain: bool,
        request: bytes,
        send_at: float,
        first_wake: float,
        timeout: float,
        char: float,
        expect: int,
        short_len: int,
        look: bool = True,
    ) -> None: ...

    def result(self) -> XferResult | None: ...

    def cancel(self) -> None: ...

    def close(self) -> None: ...


def check_plan(
    request: bytes, first_wake: float, timeout: float, char: float, expect: int, short_len: int
) -> None:
    """The arguments both backends refuse, with the same messages."""
    if not request:
        raise ValueError("request must not be empty")
    if not 0 <= expect <= CAPACITY:
        raise ValueError(f"expect must be 0..{CAPACITY}, not {expect}")
    if not 0 <= short_len <= expect:
        raise ValueError(f"short_len must be 0..expect ({expect}), not {short_len}")
    if not char > 0:
        raise ValueError(f"char must be a positive number of seconds, not {char}")
    if not first_wake >= 0 or not timeout >= 0:
        raise ValueError("first_wake and timeout must be non-negative numbers of seconds")


__all__ = [
    "ANSWER",
    "CANCELLED",
    "CAPACITY",
    "ERRNO",
    "GONE",
    "SHORT",
    "STAGE_READ",
    "STAGE_WRITE",
    "STALE",
    "AsyncExchanger",
    "Exchanger",
    "XferResult",
    "check_plan",
]
