"""What the client protocol tells its driver to do next, and its counters.

`pyrtu.protocol.ClientProtocol.next_action` hands out one action at a time (one
type per stream, `Action`); a driver carries it out and reports back:

`Send` ``(data)``
    write ``data`` now, then report its end with ``transmitted(end, start)``.
`Wait` ``(until, listen, needed)``
    ``listen`` true: wait for input until ``until`` (wake as soon as bytes come)
    and read them; false: sleep until ``until`` whatever comes (bytes arriving
    meanwhile are useless before then: the rest of a predicted answer, or input
    on a line that must stay quiet first), then read what is there.  Either
    way report what was read (``b""``: nothing) with ``wait_done(data, now)``.
    ``until`` may be in the past: read what is there without waiting.
    ``needed``: the bytes the protocol still awaits (a lower bound); 0: none
    (a wait for the send time, a look for stale input), so that a driver may as
    well wake on input (it is stale) and need not expect any after the wait.
`Xfer` ``(data, send_at, first_wake, timeout, expect, short_len)``
    only for a driver that asks (``next_action(now, xfer=True)``), in place of
    the look, `Send` and `Wait` steps of a repeated request on a timed RTU line
    (its answer's length learned, no echo): `pyrtu.drivers.xfer.XferRunner` carries the
    steps out in one call, with the protocol's times.  The driver reports what it
    saw with the same inputs: input found at the send time (nothing sent) with
    ``wait_done(data, now)``; else ``transmitted(end, start)``, then the first
    read's bytes and the rest with ``receive_data`` at their times.
`Done` ``(value, error, end)``
    the transaction is over: ``result()`` returns ``value`` or raises ``error``;
    ``end`` is when the answer's last byte arrived (None without an answer).

Time is monotonic seconds throughout (``time.monotonic``; the asyncio loop's
``time()`` is the same clock).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Any, NamedTuple

from pyrtu.core._deprecated import renamed
from pyrtu.pdu.requests import answer_pdu as answer_pdu

DISCARD_REASONS = (
    "crc",
    "t1.5",
    "overflow",
    "unknown_function",
    "truncated",
    "stale",
    "unexpected",
)
#: ``decode(response_pdu)``: the result, or `FrameError` for data that is not the answer
Decoder = Callable[[bytes], Any]


class ClientState(enum.Enum):
    """Where a `ClientProtocol` stands in its transaction (`ClientProtocol.state`)."""

    IDLE = "idle"
    QUIET = "quiet"
    SEND = "send"
    ANSWER = "answer"
    DONE = "done"


class Send(NamedTuple):
    """Write ``data`` now, then call ``transmitted(end, start)``."""

    data: bytes


class Wait(NamedTuple):
    """Wait until ``until`` (monotonic seconds; may be past: no wait), then read
    what the port has and call ``wait_done(data, now)``.  ``listen``: wake as soon
    as input comes; else sleep until ``until`` whatever comes.  ``needed``: the
    bytes still awaited (0: none, input now would be stale)."""

    until: float
    listen: bool
    needed: int


class Xfer(NamedTuple):
    """Look for stale input at ``send_at`` (then send nothing), send ``data``, read
    first at ``first_wake`` seconds after the end of transmission and on until
    ``expect`` bytes (``short_len`` for an exception answer) or ``timeout`` seconds
    after it; then report as the module docstring says."""

    data: bytes
    send_at: float
    first_wake: float
    timeout: float
    expect: int
    short_len: int


class Done(NamedTuple):
    """The transaction is over: ``value`` or ``error``; ``end``: when the answer's
    last byte arrived (None: no answer, e.g. a broadcast or an error)."""

    value: Any
    error: BaseException | None
    end: float | None

    def result(self) -> Any:
        """The value, or raise the transaction's error."""
        if self.error is not None:
            raise self.error
        return self.value


#: what `ClientProtocol.next_action` hands the driver
Action = Send | Wait | Xfer | Done


#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(__name__, {"Exchange": ("pyrtu.protocol.client_actions", "Xfer")})


def new_counters() -> dict[str, int]:
    """The master's counters, all zero."""
    keys = ["requests", "responses", "broadcasts", "exceptions", "timeouts", "crc_errors"]
    keys += ["frame_errors", "echo_mismatches", "retries", "discarded_bytes"]
    keys += [f"discarded_{r}" for r in DISCARD_REASONS]
    return dict.fromkeys(keys, 0)


__all__ = [
    "DISCARD_REASONS",
    "Action",
    "ClientState",
    "Decoder",
    "Done",
    "Send",
    "Wait",
    "Xfer",
    "answer_pdu",
    "new_counters",
]
