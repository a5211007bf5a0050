"""The sans-I/O Modbus client (master) protocol: one transaction at a time on a line.

No clock, no port, no sleeps: time is an input (``now``, seconds on a monotonic
clock) and the driver does the I/O.  The protocol tells its driver the one next
thing to do (`ClientProtocol.next_action`: `Send`, `Wait`, `Done`, described in
`pyrtu.protocol.client_actions`), as aioquic's connection hands out its datagrams and
its timer.  Every decision is the protocol's: when to look for stale input
before sending, how long to sleep while an answer comes in (``ready_at``, in
`pyrtu.protocol.client_timing`: its predicted length, the slave's learned turnaround),
when to wake on input, when the attempt ends.

States: ``IDLE`` -> ``QUIET`` (waiting for the earliest send time: t3.5 after the
line went quiet, the broadcast turnaround, the settling time after a failure;
bytes that arrive now are stale and restart the silence) -> ``SEND`` (the ADU is
ready) -> ``ANSWER`` (the echo of an echoing adapter first, then the answer, fed
to the framer) -> ``DONE`` (a result or a typed error).  A failed attempt with
retries left goes back to ``QUIET``.  ``abort(now)`` (a cancelled driver) ends the
transaction and makes the next one wait out a late answer.  The lower-level
inputs (``receive_data``, ``handle_timer``, ``deadline``) stay available to a
driver that keeps its own loop.

Frames that are not the answer (another slave or function, data the decoder
refuses, frames damaged on the line) are dropped and counted; the wait goes on
for a short settling time in case the real answer follows, then the attempt
ends with `FrameError`.  Nothing valid within ``timeout`` after the end of
transmission: `NoResponseError`.  An exception response ends it at once with
`ExceptionResponseError` (never retried).  An echo that differs from the request
or does not come back: `BusFault`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from types import ModuleType
from typing import Any

from pyrtu.core import _backend
from pyrtu.core._deprecated import renamed, warn_renamed
from pyrtu.core.ascii import ascii_message, encode_ascii, make_framer
from pyrtu.core.feed import feed_all
from pyrtu.core.frames import ERROR_BY_CODE
from pyrtu.core.framing import FramerCore
from pyrtu.core.line import LineConfig
from pyrtu.pdu.errors import BusFault, ExceptionResponseError, FrameError, NoResponseError
from pyrtu.pdu.functions import function_name
from pyrtu.protocol.client_actions import (
    Action,
    ClientState,
    Decoder,
    Done,
    Send,
    Wait,
    answer_pdu,
    new_counters,
)
from pyrtu.protocol.client_timing import LATE_WAKE_CHAR, WAKE_STEP
from pyrtu.protocol.client_xfer import XferSteps

log = logging.getLogger("pyrtu.drivers.master")

#: old names, deprecated (each use warns, naming the new one)
__getattr__ = renamed(__name__, {"State": ("pyrtu.protocol.client_actions", "ClientState")})
_debug = log.isEnabledFor

# module constants: an enum member lookup costs a class attribute access (3.11)
_IDLE, _QUIET, _SEND, _ANSWER, _DONE = (
    ClientState.IDLE,
    ClientState.QUIET,
    ClientState.SEND,
    ClientState.ANSWER,
    ClientState.DONE,
)
_DEBUG = logging.DEBUG
_ADUS_MAX = 1024
#: the core's error codes (RTU_ERR_*) as the discard reasons of the counters
_REASONS: tuple[str | None, ...] = tuple(r.value if r else None for r in ERROR_BY_CODE)


def _identity(pdu: bytes) -> bytes:
    return pdu


def _strip_crc(adu: bytes) -> bytes:
    return adu[:-2]


#: ASCII requests have no max_adu check (as before: the limit is RTU's)
_NO_LIMIT = 1 << 62


class ClientProtocol(XferSteps):
    """A Modbus master's transactions on one line, for a driver to carry out::

        proto = ClientProtocol(LineConfig(baudrate=9600), timeout=0.5)
        proto.start(1, pdu.read_request(3, 0, 10), decode, now())
        while True:
            action = proto.next_action(now())
            if isinstance(action, Send):         # the line is quiet: transmit
                start, end = port.write(action.data)
                proto.transmitted(end, start)    # end of transmission is an input
            elif isinstance(action, Wait):       # sleep, or wait for input; read
                proto.wait_done(read(action), now())
            else:                                # Done
                value = action.result()          # or raises the transaction's error
                break

    (docs/PROTOCOL.md has a working one.)  ``line``: the `LineConfig`;
    ``timeout``: seconds from the end of transmission to a valid answer;
    ``retries``: repeats after `NoResponseError` and `FrameError`; ``echo``: the
    adapter reads back what it sends (RS-485 without echo suppression);
    ``broadcast_delay``: the silence after a broadcast (Serial Line V1.02, 2.4.1
    "turnaround delay"); ``backend``: the framer's backend.
    """

    def __init__(
        self,
        line: LineConfig,
        *,
        timeout: float = 1.0,
        retries: int = 0,
        echo: bool = False,
        broadcast_delay: float = 0.1,
        backend: ModuleType | None = None,
    ) -> None:
        self.line = line
        self.timeout = timeout
        self.retries = retries
        self.echo = echo
        self.broadcast_delay = broadcast_delay
        self._backend = backend or _backend.active
        self.counters = new_counters()
        #: RTU ADUs already built, by (slave, PDU): a poller repeats the same requests
        self._adus: dict[tuple[int, bytes], bytes] = {}
        #: per request ADU: the length of its last answer (see ready_at)
        self._sizes: dict[bytes, int] = {}
        self._configure(line)
        self.state = _IDLE
        # the line, across transactions
        self.tx_end = 0.0  # end of our last transmission
        self.last_rx = 0.0  # arrival of the last byte we read
        self.quiet_until = 0.0  # broadcast turnaround
        self.failed_at = 0.0  # when an attempt failed (a late answer may follow)
        self._abandoned_until = 0.0  # the deadline of the answer `abort` gave up on
        #: when the last byte of the latest answer arrived (None before one)
        self.answer_end: float | None = None
        # the transaction
        self._slave = 0
        self._fc = 0
        self._adu = b""
        self._decode: Decoder | None = None
        self._attempt = 0
        self._give_up = 0.0  # QUIET: send anyway after a babbling line
        self._echo_left = b""
        self._end = 0.0  # ANSWER: end of transmission
        self._limit = 0.0  # ANSWER: when the attempt ends without an answer
        self._bad: FrameError | None = None
        self._heard = False  # ANSWER: a byte came after the request
        self._result: Any = None
        self._error: Exception | None = None
        self._dbg = False  # debug logging on for this transaction
        self._checked = False  # SEND: the driver just read and found no input
        self._nap = False  # ANSWER: sleep on ready_at before waiting for input
        #: per slave: how long past t3.5 its answers start (see _learn_turnaround)
        self._turn: dict[int, float] = {}
        #: per slave: whole answers in first reads in a row (see _woke_late)
        self._late_runs: dict[int, int] = {}

    def set_line(self, line: LineConfig) -> None:
        """A new line configuration (new length rules); between transactions only."""
        if self.state not in (_IDLE, _DONE):
            raise RuntimeError(f"a transaction is in progress ({self.state.value})")
        self._configure(line)

    def _configure(self, line: LineConfig) -> None:
        self.line = line
        #: the inter-frame silence kept before a request (seconds; 0: none)
        self.gap = line.frame_gap
        self.settle = max(0.02, 3 * self.gap)
        self._char = line.char_time
        #: learn answer lengths where ready_at uses them (a timed line)
        self._one_wake = self.gap > 0
        #: see ready_at: how wake-ups late by a character or more settle on the
        #: answer's end; the characters an Xfer's first read comes early by
        slow = self._char >= LATE_WAKE_CHAR
        self._wake_step = WAKE_STEP if slow else self._char / 4
        self._early_chars = 0 if slow else 1
        #: a repeated request may go as one `Xfer` (a timed, lenient RTU line)
        self._can_xfer = self._one_wake and line.mode == "rtu" and not line.strict
        self._adus.clear()
        self._sizes.clear()
        # what differs between RTU and ASCII, chosen once per line: the framer's core
        # (the same feed/take interface for both, driven directly: events as the
        # core's tuples, no Frame objects), how a request is wrapped and checked, how
        # a frame the core checked becomes address + PDU
        self._core: FramerCore = make_framer(line, "master", self._backend).core
        self._wrap: Callable[[bytes], bytes]
        self._message: Callable[[bytes], bytes]
        if line.mode == "ascii":
            self._wrap, self._message, self._max_adu = encode_ascii, ascii_message, _NO_LIMIT
        else:
            self._wrap, self._message = self._backend.add_crc, _strip_crc
            self._max_adu = line.max_adu

    # ------------------------------------------------------------- transaction

    @property
    def done(self) -> bool:
        return self.state is _DONE

    def encode(self, slave: int, pdu: bytes) -> bytes:
        """The ADU of ``pdu`` to ``slave`` in the line's mode; ValueError past max_adu."""
        adu = self._wrap(bytes((slave,)) + pdu)
        if len(adu) > self._max_adu:
            raise ValueError(f"{function_name(pdu[0])}: a {len(adu)}-byte request exceeds max_adu")
        return adu

    def start(self, slave: int, pdu: bytes, decode: Decoder | None, now: float) -> None:
        """Begin a transaction: ``pdu`` (function code + data, from the PDU builders) to
        ``slave``.  ``decode(response_pdu)`` gives the result and raises `FrameError`
        for data that cannot be the answer; None: no answer is awaited (a broadcast,
        or FC 08 sub-function 4), the result is None.  Raises ValueError (nothing
        is sent) for a request longer than ``max_adu``."""
        if self.state not in (_IDLE, _DONE):
            raise RuntimeError(f"a transaction is in progress ({self.state.value})")
        key = (slave, pdu)  # the hot path: encode() cached
        adu = self._adus.get(key)
        if adu is None:
            adu = self.encode(slave, pdu)  # raises its ValueError past max_adu
            if len(self._adus) >= _ADUS_MAX:
                self._adus.clear()
            self._adus[key] = adu
        self._adu = adu
        self._slave, self._fc, self._decode = slave, pdu[0], decode
        self._attempt = 0
        self._checked = False
        self._result = self._error = None
        self._give_up = now + self.timeout
        ready = self.send_at() if self.gap > 0 or self.failed_at else self.quiet_until
        # the line is quiet already (the common case): SEND at once
        self.state = _SEND if ready <= now else _QUIET

    def _begin_attempt(self, now: float) -> None:
        self.state = _QUIET
        self._give_up = now + self.timeout
        self._check_quiet(now)

    def _check_quiet(self, now: float) -> None:
        if self.state is _QUIET and (self.send_at() <= now or now >= self._give_up):
            self.state = _SEND

    def data_to_send(self) -> bytes:
        """SEND: the ADU to transmit now (a driver reads pending input first and feeds
        it with receive_data, which may move the protocol back to QUIET)."""
        if self.state is not _SEND:
            raise RuntimeError(f"nothing to send ({self.state.value})")
        return self._adu

    def transmitted(self, end: float, start: float | None = None) -> None:
        """The ADU went out; ``end``: when its transmission ended (``start``: when it
        began, for the log)."""
        if self.state is not _SEND:
            raise RuntimeError(f"nothing was to be sent ({self.state.value})")
        self._went(end)
        # once per transaction (after the write: off the critical path); the hot path
        # logs nothing
        self._dbg = _debug(_DEBUG)
        if self._dbg:
            log.debug(
                "TX slave %d fc %d: %s (%.3f ms on the line)",
                self._slave,
                self._fc,
                self._adu.hex(" "),
                (end - (end if start is None else start)) * 1e3,
            )
        self._echo_left = self._adu if self.echo else b""
        self._heard = False
        if self._decode is None:
            self._core.reset()
            self.counters["broadcasts"] += 1
            self.quiet_until = end + self.broadcast_delay
            if not self._echo_left:
                self._finish(None)
                return
        else:
            self._core.expect(self._adu)  # a fresh framer, told of the request
        self.state = _ANSWER
        self._nap = True

    def _went(self, end: float) -> None:
        """SEND: the request's transmission ended at ``end`` (what `transmitted` and
        an `Xfer`'s short cut both record): the silence and the answer's deadline
        count from it."""
        self.quiet_until = self.failed_at = 0.0
        self.tx_end = self._end = end
        self._limit = end + self.timeout
        self._bad = None
        self.counters["requests"] += 1

    # ------------------------------------------------------------- inputs

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes read at ``now``."""
        if not data:
            return
        self.last_rx = now
        state = self.state
        if state is not _ANSWER:
            # before the request (or between transactions): a late answer, noise
            self._discard("stale", len(data))
            log.debug("stale input dropped: %s", data.hex(" "))
            self._checked = False
            if state is _SEND:
                self.state = _QUIET
                self._check_quiet(now)
            return
        first = not self._heard
        self._heard = True
        if self._echo_left:
            data = self._eat_echo(data, now)
            if self.state is _DONE:
                return
            if self._decode is None:
                if data:
                    self._discard("stale", len(data))
                if not self._echo_left:
                    self._finish(None)
                return
            if not data:
                return
        self._feed(data, now)
        if self.state is _ANSWER:
            self._nap = True
            if self._bad is not None:
                self._limit = min(self._end + self.timeout, now + self.settle)
            elif first and not self.echo and self.gap > 0:
                self._learn_turnaround(len(data), now)
        elif first and self._one_wake and not self.echo:
            self._woke_late()

    def next_action(
        self, now: float, xfer: bool = False, *, exchange: bool | None = None
    ) -> Action:
        """What the driver does next (see the module docstring): `Send` the request,
        `Wait` (a sleep on ``ready_at`` while an answer comes in, a wait for input
        until the attempt's deadline, a sleep to the send time, or a look for stale
        input just before the request goes), or `Done` (then the protocol is idle
        again).  Call it after each of the protocol's inputs.  ``xfer``: the
        driver can carry out an `Xfer` (`pyrtu.drivers.xfer`), handed out instead
        of those steps where the request is one whose answer length is known."""
        state = self.state
        if exchange is not None:  # the old keyword, deprecated
            warn_renamed("next_action(exchange=...)", "next_action(xfer=...)")
            xfer = exchange
        if xfer and (state is _SEND or state is _QUIET):
            plan = self._xfer_plan()
            if plan is not None:
                return plan
        if state is _ANSWER:
            needed = self.needed()
            if self._nap:  # bytes are due: sleep until they can all be in
                self._nap = False
                if self.gap > 0 and (until := self._ready_at(now, needed)) > now:
                    return Wait(until, False, needed)
            return Wait(self.deadline() or now, True, needed)
        if state is _SEND:
            if self._checked:
                return Send(self._adu)
            return Wait(now, False, 0)  # pending input first: stale, it restarts the silence
        if state is _QUIET:
            return Wait(min(self.send_at(), self._give_up), False, 0)
        if state is _DONE:
            self.state = _IDLE
            error, self._error = self._error, None
            answered = error is None and self._decode is not None
            return Done(self._result, error, self.answer_end if answered else None)
        raise RuntimeError("no transaction (start one first)")

    def wait_done(self, data: bytes, now: float) -> None:
        """A `Wait` ended at ``now`` with ``data`` read (b"": none came)."""
        if data:
            self.receive_data(data, now)
        else:
            self._checked = True
            self.handle_timer(now)

    def handle_timer(self, now: float) -> None:
        """Time passed up to ``now`` (call it at ``deadline()``)."""
        state = self.state
        if state is _QUIET:
            self._check_quiet(now)
            return
        if state is not _ANSWER:
            return
        if not self._echo_left:
            core = self._core
            timer = core.deadline()
            if timer is not None and now >= timer / 1e6:
                core.handle_timer(round(now * 1_000_000))
                self._drain(now)
                if self.state is not _ANSWER:
                    return
        if now >= self._limit:
            self._fail_attempt(now)

    def deadline(self) -> float | None:
        """When ``handle_timer`` must run: the send time (QUIET), the end of the wait
        for the answer (ANSWER), or None."""
        state = self.state
        if state is _QUIET:
            return min(self.send_at(), self._give_up)
        if state is not _ANSWER:
            return None
        if self._echo_left or not self._heard:
            return self._limit  # no byte of the answer yet: the framer has no timer
        deadline = self._core.deadline()
        return self._limit if deadline is None else min(deadline / 1e6, self._limit)

    def abort(self, now: float) -> None:
        """The driver gave up on the transaction (cancelled): the line keeps what it
        knows, and the next transaction waits out a late answer."""
        if self.state in (_IDLE, _DONE):
            return
        if self.state is _ANSWER:
            self.failed_at = now
            self._abandoned_until = self._limit
        self.state = _IDLE

    def abandoned_xfer(self, end: float, last_rx: float, now: float) -> None:
        """A cancelled `Xfer` (the transaction was given up on while the driver
        carried it out) had sent the request, its transmission ending at ``end``, and
        read until ``last_rx`` (0.0: nothing): as `abort` during the answer, a late
        answer may follow until the request's deadline."""
        self.tx_end = end
        if last_rx > self.last_rx:
            self.last_rx = last_rx
        self.failed_at = now
        self._abandoned_until = end + self.timeout

    def abandoned_exchange(self, end: float, last_rx: float, now: float) -> None:
        """Deprecated: `abandoned_xfer`."""
        warn_renamed("ClientProtocol.abandoned_exchange", "ClientProtocol.abandoned_xfer")
        self.abandoned_xfer(end, last_rx, now)

    def late_answer_over_at(self) -> float:
        """When the answer of a transaction given up on (`abort`) is over, as a driver
        that hands the line on (closes the port) must wait: the line quiet for
        ``settle`` after the last byte heard since, or the abandoned answer's deadline
        without a byte.  0.0: no answer is owed."""
        if not self.failed_at:
            return 0.0
        if self.last_rx > self.failed_at:
            return self.last_rx + self.settle
        return max(self._abandoned_until, self.failed_at + self.settle)

    def result(self) -> Any:
        """DONE: the decoded answer (None for a broadcast), or raise the error."""
        if self.state is not _DONE:
            raise RuntimeError(f"the transaction is not done ({self.state.value})")
        self.state = _IDLE
        if self._error is not None:
            error, self._error = self._error, None
            raise error
        return self._result

    # ------------------------------------------------------------- internals

    def _discard(self, reason: str, size: int) -> None:
        c = self.counters
        c["discarded_bytes"] += size
        c[f"discarded_{reason}"] = c.get(f"discarded_{reason}", 0) + size

    def _finish(self, value: Any) -> None:
        self._result = value
        self.state = _DONE

    def _fail(self, error: Exception, now: float) -> None:
        """End with ``error``; ``now`` (0: none) starts the settling a late answer needs."""
        self._error = error
        self.failed_at = now
        self.state = _DONE

    def _eat_echo(self, data: bytes, now: float) -> bytes:
        expected = self._echo_left
        n = min(len(data), len(expected))
        if data[:n] != expected[:n]:
            self.counters["echo_mismatches"] += 1
            adu = self._adu
            got = adu[: len(adu) - len(expected)] + data[:n]
            self._fail(
                BusFault(
                    f"{function_name(self._fc)}: slave {self._slave}: echo mismatch: "
                    f"sent {adu.hex(' ')}, read back {got.hex(' ')}",
                    self._slave,
                    self._fc,
                ),
                now,
            )
            return b""
        self._echo_left = expected[n:]
        return data[n:]

    def _feed(self, data: bytes, now: float) -> None:
        """Bytes into the framer's core, its events handled as they come (a silence
        before the new bytes may end what is buffered: the core takes fewer); once
        the transaction is done the rest is left unfed."""
        core = self._core
        now_us = round(now * 1_000_000)
        took = core.feed(data, now_us)
        if not self._drain(now) and took < len(data):  # the rest: feed until taken
            feed_all(lambda chunk: core.feed(chunk, now_us), data[took:], lambda: self._drain(now))

    def _drain(self, now: float) -> bool:
        """The core's events, as ``take()`` gives them: (error, end_us, adu); True once
        the transaction is done."""
        take = self._core.take
        message = self._message
        while self.state is _ANSWER and (ev := take()) is not None:
            error, end_us, adu = ev
            reason = _REASONS[error]
            self._event(now, reason, b"" if reason else message(adu), len(adu), end_us / 1e6)
        return self.state is not _ANSWER

    def _event(
        self, now: float, reason: str | None, message: bytes, size: int, end: float | None
    ) -> None:
        """One frame or discard event of the answer phase."""
        slave, fc = self._slave, self._fc
        c = self.counters
        if reason is None and message[0] == slave and message[1] & 0x7F == fc:
            # the answer (the hot path first)
            if self._dbg:
                log.debug(
                    "RX slave %d fc %d: %s (%.3f ms)",
                    slave,
                    fc,
                    message.hex(" "),
                    (now - self._end) * 1e3,
                )
            if message[1] & 0x80:
                self._exception_answer(message, end)
                return
            decode = self._decode or _identity
            try:
                value = decode(message[1:])
            except FrameError as exc:
                self._settle(now)
                self._discard("unexpected", size)
                self._bad = self._bad or FrameError(f"slave {slave}: {exc}", slave, fc)
                return
            c["responses"] += 1
            self.answer_end = end
            self._result = value  # _finish inlined (the hot path)
            self.state = _DONE
            if self._one_wake and self._sizes.get(self._adu) != size:  # see ready_at
                if len(self._sizes) >= 4096:
                    self._sizes.clear()
                self._sizes[self._adu] = size
            return
        self._not_the_answer(now, reason, message, size)

    def _exception_answer(self, message: bytes, end: float | None) -> None:
        """The slave's exception response to our request (function | 0x80, code)."""
        self.counters["exceptions"] += 1
        if self._decode is answer_pdu:  # an exchange: the answer is its value
            self.answer_end = end
            self._finish(message[1:])
            return
        code = message[2] if len(message) > 2 else 0
        # answered: no late answer to wait out (failed_at stays 0)
        self._fail(ExceptionResponseError(self._slave, self._fc, code), 0.0)

    def _not_the_answer(self, now: float, reason: str | None, message: bytes, size: int) -> None:
        """Bytes discarded, or a frame that is not the answer: counted, remembered as
        the error should no answer come, and a settling time to wait."""
        slave, fc = self._slave, self._fc
        self._settle(now)
        if reason is not None:
            self._discard(reason, size)
            if reason == "crc":
                self.counters["crc_errors"] += 1
            self._bad = self._bad or FrameError(
                f"{function_name(fc)}: slave {slave}: {size} bytes discarded ({reason})",
                slave,
                fc,
            )
            return
        self._discard("unexpected", size)
        log.debug("RX dropped (not the answer): %s", message.hex(" "))
        self._bad = self._bad or FrameError(
            f"{function_name(fc)}: slave {slave}: got a frame from slave {message[0]} "
            f"function 0x{message[1]:02X} instead of the answer",
            slave,
            fc,
        )

    def _settle(self, now: float) -> None:
        """A frame that was not the answer: wait at most the settling time for it."""
        limit, settled = self._end + self.timeout, now + self.settle
        self._limit = limit if limit <= settled else settled  # min() without the call

    def _fail_attempt(self, now: float) -> None:
        """No answer by the limit: the attempt's error; retry when allowed."""
        slave, fc = self._slave, self._fc
        where = function_name(fc)
        c = self.counters
        error: FrameError | NoResponseError
        if self._echo_left:
            c["echo_mismatches"] += 1
            self._fail(
                BusFault(
                    f"{where}: slave {slave}: the echo of the request did not come back", slave, fc
                ),
                now,
            )
            return
        if self._bad is not None:
            c["frame_errors"] += 1
            error = self._bad
        else:
            c["timeouts"] += 1
            error = NoResponseError(
                f"{where}: slave {slave}: no response within {self.timeout} s", slave, fc
            )
        self.failed_at = now
        if self._attempt < self.retries:
            self._attempt += 1
            c["retries"] += 1
            log.debug("retry %d of %d after: %s", self._attempt, self.retries, error)
            self._begin_attempt(now)
            return
        self._fail(error, now)


__all__ = [
    "Action",
    "ClientProtocol",
    "ClientState",
    "Done",
    "Send",
    "Wait",
    "new_counters",
]
