"""When the client protocol may send and when the bytes of an answer can be in.

The timing half of `pyrtu.protocol.ClientProtocol` (a base class: it reads the
protocol's state): the earliest send time (t3.5 after the line went quiet, the
broadcast turnaround, the settling time after a failure), the bytes an answer
still needs, and the sleep that reads them in as few wake-ups as the line
allows (``ready_at``, which `ClientProtocol.next_action` turns into a `Wait`; for a
repeated request, `pyrtu.protocol.client_xfer` puts the same times in one
`Xfer`).
"""

from __future__ import annotations

from typing import Any

from pyrtu.core.framing import FramerCore
from pyrtu.protocol.client_actions import ClientState

_ANSWER = ClientState.ANSWER

#: where a character is shorter than this (above 19200 baud), a timed wake-up is
#: typically a character or more late: a whole answer in the wake-up's read lowers
#: the turnaround by a quarter character (`AnswerTiming._woke_late`); slower, a
#: `Wait` wakes a character early and leaves the last byte to a wait for input, and
#: an `Xfer` reads at the answer's predicted end (one wake-up fewer, at most a
#: wake-up's lateness on the silence that follows), lowering it by `WAKE_STEP`
LATE_WAKE_CHAR = 0.0005
#: seconds a whole answer in the first read lowers the turnaround on a line slower
#: than `LATE_WAKE_CHAR` (about half a timed wake-up's lateness on a loaded VM): the
#: reads settle at the answer's end instead of staying late after one slow answer
WAKE_STEP = 25e-6
#: whole answers in first reads in a row, after the first `_PLAIN_STEPS`, double the
#: step each (up to 2**`_MAX_DOUBLINGS` times it): a turnaround learned from one slow
#: answer (a slave's very first, say: its thread or its caches cold; 2 ms on the
#: virtual bus) comes down in about ten transactions instead of a hundred, while an
#: answer in two reads resets the step
_PLAIN_STEPS = 3
_MAX_DOUBLINGS = 12


class AnswerTiming:
    """The timing decisions of a `ClientProtocol` (see the module docstring)."""

    # the protocol's state these read (set by ClientProtocol)
    state: ClientState
    gap: float
    timeout: float
    echo: bool
    _give_up: float
    _fc: int
    settle: float
    quiet_until: float
    tx_end: float
    last_rx: float
    failed_at: float
    _char: float
    _one_wake: bool
    _wake_step: float
    _slave: int
    _adu: bytes
    _decode: Any
    _core: FramerCore
    _heard: bool
    _echo_left: bytes
    _end: float
    _limit: float
    _turn: dict[int, float]
    _late_runs: dict[int, int]
    _sizes: dict[bytes, int]

    def send_at(self) -> float:
        """QUIET: the earliest time the request may go out."""
        ready = self.quiet_until
        if self.gap > 0:
            ready = max(ready, self.tx_end + self.gap, self.last_rx + self.gap)
        if self.failed_at:
            ready = max(ready, self.failed_at + self.settle, self.last_rx + self.settle)
        return ready

    def _learn_turnaround(self, size: int, now: float) -> None:
        """The first bytes of an answer still coming: its first byte arrived about
        ``size`` characters before ``now`` (the slave sends its characters back to
        back, Serial Line V1.02 2.5.1.1), so the slave took that long past t3.5 to
        answer (an upper bound within a character: the bytes were read at ``now``,
        at or after the last one came).  Kept per slave as a slowly rising minimum
        of these estimates, so that `ready_at` puts the first sleep where the first
        bytes are in (a slave that answers sooner lowers it at once)."""
        turn = now - size * self._char - (self._end + self.gap)
        turn = turn if turn > 0.0 else 0.0
        old = self._turn.get(self._slave)
        self._late_runs.pop(self._slave, None)
        if old is None or turn <= old:
            if old is None and len(self._turn) >= 256:
                self._turn.clear()
                self._late_runs.clear()
            self._turn[self._slave] = turn
        else:
            self._turn[self._slave] = old + (turn - old) / 16

    def _woke_late(self) -> None:
        """The whole answer came in the first read (a `ready_at` wake-up, or an
        `Xfer`'s first read): it was in before the read, by an unknown time.  A
        little earlier next time (a quarter character; `WAKE_STEP` on a line slower
        than `LATE_WAKE_CHAR`; see `ready_at`), twice as much for each further one
        in a row after the first `_PLAIN_STEPS` (up to 2**`_MAX_DOUBLINGS` times)."""
        slave = self._slave
        old = self._turn.get(slave)
        if old is not None:
            run = self._late_runs.get(slave, 0) + 1
            self._late_runs[slave] = run
            doublings = min(run - _PLAIN_STEPS, _MAX_DOUBLINGS)
            step = self._wake_step * (1 << doublings) if doublings > 0 else self._wake_step
            lower = old - step
            self._turn[slave] = lower if lower > 0.0 else 0.0

    def turnaround(self, slave: int) -> float | None:
        """The slave's learned turnaround past t3.5 (seconds; see `ready_at`), None
        before one of its answers was seen arriving on a timed line."""
        return self._turn.get(slave)

    def ready_at(self, now: float) -> float:
        """ANSWER: when the bytes still needed can all be in, so that a driver sleeps
        until then instead of waking per byte (`next_action` uses it).

        Before any byte of the answer: from the end of transmission plus t3.5 (the
        slave keeps that silence, Serial Line V1.02 2.5.1.1; not with an echo) plus
        the slave's learned `turnaround`, ``needed()`` character times; for a
        request whose answer was seen before, that answer's length less one
        character (one wake-up for the whole answer).  A wake-up that finds the
        whole answer in was late by an unknown time (the next t3.5 counts from that
        read): the turnaround is lowered a little each time (`_woke_late`), so that
        the wake-ups settle around the answer's end; one that comes early reads the
        bytes still coming and learns the turnaround again from them.
        (Without that, a wake-up a few characters late at 115200 on the virtual
        bus cost 3 % of the transactions.)  Once bytes came: ``needed() - 1``
        characters from now, the last byte left to a wait for input (read as it
        comes: the next silence counts from the answer's real end).  Never past
        the end of the attempt.  ``now`` in other states and on a line without
        wire timing (t3.5 = 0: bytes come in bursts, not at the character rate)."""
        if self.state is not _ANSWER or self.gap <= 0:
            return now
        return self._ready_at(now, self.needed())

    def _ready_at(self, now: float, needed: int) -> float:
        """`ready_at` in ANSWER on a timed line, ``needed()`` given."""
        start = now
        if not self._heard and not self._echo_left:
            start = max(now, self._end + self.gap + self._turn.get(self._slave, 0.0))
            if self._one_wake:
                size = self._sizes.get(self._adu, 0)
                if size > needed:
                    needed = size - 1
        elif needed:
            # a character early (measured on the virtual bus at 115200: the delay
            # past t3.5 from 145 to 62 µs, the wire efficiency 0.977 -> 0.995)
            needed -= 1
        return min(start + needed * self._char, self._limit)

    def needed(self) -> int:
        """ANSWER: bytes that must still arrive before the answer can be complete (a
        lower bound: the echo still expected plus the framer's ``needed()``); 0 when
        unknown (ASCII, an unknown layout) or in another state."""
        if self.state is not _ANSWER:
            return 0
        if self._decode is None:
            return len(self._echo_left)
        return len(self._echo_left) + self._core.needed()
