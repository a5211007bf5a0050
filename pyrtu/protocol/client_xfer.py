"""A repeated request as one `Xfer`: the plan the client protocol hands out, and
the report it takes back.

The xfer half of `pyrtu.protocol.ClientProtocol` (a base class, as
`pyrtu.protocol.client_timing.AnswerTiming` is: it reads and sets the protocol's
state).  ``_xfer_plan`` gives a driver that asked (``next_action(now,
xfer=True)``) the whole transaction of a repeated request on the times `send_at`
and `ready_at` would give; ``xfer_done`` takes its report.

``xfer_done`` is what the steps the xfer stands for would report (the look at
the send time that found the line quiet, ``transmitted``, the first read's bytes
and the rest with ``receive_data``), with one short cut that decides nothing new:
bytes of exactly the learned answer length whose CRC checks and whose address and
function are the request's are the one frame the framer would make of them (they
are the whole of what came after the request), so they go to the decoder without
it.  Anything else (fewer or more bytes, a CRC that fails, another slave or
function, an exception answer, data the decoder refuses, debug logging on) takes
the steps one by one.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from pyrtu.core._deprecated import warn_renamed
from pyrtu.pdu.errors import FrameError
from pyrtu.protocol.client_actions import ClientState, Xfer
from pyrtu.protocol.client_timing import AnswerTiming

_QUIET, _SEND, _DONE = ClientState.QUIET, ClientState.SEND, ClientState.DONE
_debug = logging.getLogger("pyrtu.drivers.master").isEnabledFor
_DEBUG = logging.DEBUG
#: functions whose answer's length follows from the request ([MB] 6.1-6.6, 6.11,
#: 6.12, 6.16, 6.17): a learned length holds for the next answer (see `Xfer`)
_FIXED_ANSWER = frozenset((1, 2, 3, 4, 5, 6, 15, 16, 22, 23))
#: an RTU exception answer: address, function | 0x80, code, CRC ([MB] 7)
_EXCEPTION_ADU = 5


class XferSteps(AnswerTiming):
    """The `Xfer` of a `ClientProtocol` (see the module docstring)."""

    # the protocol's state these read and set (besides AnswerTiming's)
    _can_xfer: bool
    _backend: Any
    counters: dict[str, int]
    answer_end: float | None
    _early_chars: int
    _bad: FrameError | None
    _dbg: bool
    _result: Any

    if TYPE_CHECKING:  # the protocol's inputs (ClientProtocol)

        def wait_done(self, data: bytes, now: float) -> None: ...

        def transmitted(self, end: float, start: float | None = None) -> None: ...

        def receive_data(self, data: bytes, now: float) -> None: ...

        def _check_quiet(self, now: float) -> None: ...

        def _went(self, end: float) -> None: ...

    def _xfer_plan(self) -> Xfer | None:
        """SEND or QUIET: the whole transaction of a repeated request, on the times
        `send_at` and `ready_at` would give (None where it does not apply: ASCII, an
        echo, strict framing, a broadcast, an answer of unknown or variable length)."""
        if not self._can_xfer or self.echo or self._decode is None:
            return None
        size = self._sizes.get(self._adu, 0)
        if size < _EXCEPTION_ADU or self._fc not in _FIXED_ANSWER:
            return None
        send_at = self.send_at() if self.state is _QUIET else 0.0
        # the first read where the answer can all be in (a character early on a fast
        # line: see LATE_WAKE_CHAR)
        chars = size - self._early_chars
        first = self.gap + self._turn.get(self._slave, 0.0) + chars * self._char
        return Xfer(
            self._adu,
            min(send_at, self._give_up),
            min(first, self.timeout),
            self.timeout,
            size,
            _EXCEPTION_ADU,
        )

    def xfer_done(
        self, start: float, end: float, data: bytes, first_n: int, first_t: float, last_t: float
    ) -> None:
        """An `Xfer` sent its request from ``start`` to ``end`` and read ``data``:
        ``data[:first_n]`` in its first read (returned at ``first_t``), the rest by
        ``last_t``.  (Input found at the send time, so that nothing was sent, is
        reported with ``wait_done(data, now)`` instead.)"""
        if self.state is _QUIET:
            self._check_quiet(start)
        if self.state is _SEND and self._answered(start, end, data, first_n, first_t, last_t):
            return
        self.wait_done(b"", start)
        self.transmitted(end, start)
        if first_n:
            self.receive_data(data[:first_n], first_t)
        if len(data) > first_n:
            self.receive_data(data[first_n:], last_t)

    def exchanged(
        self, start: float, end: float, data: bytes, first_n: int, first_t: float, last_t: float
    ) -> None:
        """Deprecated: `xfer_done`."""
        warn_renamed("ClientProtocol.exchanged", "ClientProtocol.xfer_done")
        self.xfer_done(start, end, data, first_n, first_t, last_t)

    def _answered(
        self, start: float, end: float, data: bytes, first_n: int, first_t: float, last_t: float
    ) -> bool:
        """SEND, the request went: ``data`` is the answer as the framer would take it
        (see the module docstring); then the protocol is where ``transmitted`` and
        ``receive_data`` would have left it (DONE), and True."""
        size = len(data)
        if (
            size != self._sizes.get(self._adu)
            or data[0] != self._slave
            or data[1] != self._fc
            or not self._backend.check_crc(data)
            or _debug(_DEBUG)
        ):
            return False
        try:
            value = self._decode(data[1:-2])
        except FrameError:  # the steps say what is wrong with it
            return False
        self._went(end)  # transmitted(end, start), no debug log
        self._heard = True
        self._dbg = False
        # receive_data: the bytes' arrival (the framer's end of the frame: the time
        # of the read that brought its last byte, in its microseconds)
        last = last_t if size > first_n else first_t
        self.last_rx = last
        self.answer_end = round(last * 1_000_000) / 1e6
        if 0 < first_n < size:  # the first bytes of an answer still coming
            self._learn_turnaround(first_n, first_t)
        else:  # the whole answer in the first read
            self._woke_late()
        self.counters["responses"] += 1
        self._result = value
        self.state = _DONE
        return True
