"""The master's transaction engine: one request, its answer, retries.

`Transactions` is the base of `pyrtu.Master`; it holds no public API.  See
`pyrtu.master` for the behaviour (stale input, t3.5, echo, late answers).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from . import _pdu_base as P
from .ascii import encode_ascii
from .errors import BusFault, ExceptionResponseError, FrameError, NoResponseError, PortError
from .port import Port

T = TypeVar("T")
log = logging.getLogger("pyrtu.master")
_monotonic = time.monotonic
_DISCARD_REASONS = (
    "crc",
    "t1.5",
    "overflow",
    "unknown_function",
    "truncated",
    "stale",
    "unexpected",
)

# A received event, normalised for RTU and ASCII:
# (error reason or None, message = address + PDU (b"" for a discard), size on the wire)
_Event = tuple[str | None, bytes, int]
Decoder = Callable[[bytes], T]
_name = P.function_name


def _counters() -> dict[str, int]:
    keys = ["requests", "responses", "broadcasts", "exceptions", "timeouts", "crc_errors"]
    keys += ["frame_errors", "echo_mismatches", "retries", "discarded_bytes"]
    keys += [f"discarded_{r}" for r in _DISCARD_REASONS]
    return dict.fromkeys(keys, 0)


class Transactions:
    """Request/answer exchange over a `Port` with a framer (set up by `Master`)."""

    port: Port
    mode: str
    timeout: float
    retries: int
    broadcast_delay: float
    echo: bool
    t35: float
    _settle: float
    _framer: Any
    _backend: Any
    _max_adu: int
    _check_crc: Callable[[bytes], bool]
    _lock: threading.RLock
    _counters: dict[str, int]
    _tx_end: float
    _last_rx: float
    _quiet_until: float
    _failed_at: float = 0.0  # when the last transaction failed (0: it did not)

    def _discard(self, reason: str, size: int) -> None:
        c = self._counters
        c["discarded_bytes"] += size
        c[f"discarded_{reason}"] = c.get(f"discarded_{reason}", 0) + size

    def _encode(self, slave: int, request: bytes) -> bytes:
        message = bytes((slave,)) + request
        if self.mode == "ascii":
            return encode_ascii(message)
        adu: bytes = self._backend.add_crc(message)
        if len(adu) > self._max_adu:
            raise ValueError(
                f"{P.function_name(request[0])}: a {len(adu)}-byte request exceeds max_adu"
            )
        return adu

    def _before_send(self) -> None:
        """Keep the inter-frame silence and the broadcast delay; bytes that arrive
        meanwhile are stale (a late answer, noise) and restart the silence."""
        port = self.port
        stale = port.read(0)
        if not stale and not self._quiet_until and self.t35 <= 0 and not self._failed_at:
            return  # the common case on a link without wire timing: one poll
        give_up = _monotonic() + self.timeout
        while True:
            now = _monotonic()
            if stale:
                self._stale(stale, now)
                stale = port.read(0) if now < give_up else b""
                if stale:
                    continue
            ready = self._quiet_until
            if self.t35 > 0:
                ready = max(ready, self._tx_end + self.t35, self._last_rx + self.t35)
            if self._failed_at:
                # after a failed transaction a late answer may still be on its way:
                # a settling silence keeps it from meeting the next request
                ready = max(ready, self._failed_at + self._settle, self._last_rx + self._settle)
            if ready <= now or now >= give_up:
                break
            stale = port.read(ready - now)
        self._quiet_until = self._failed_at = 0.0

    def _let_settle(self) -> None:
        """After a collision: drop what still comes (the slave may answer the garbled
        request) until the line is quiet, so the next transaction starts clean."""
        give_up = _monotonic() + self.timeout
        while (now := _monotonic()) < give_up:
            chunk = self.port.read(min(self._settle, give_up - now))
            if not chunk:
                break
            self._stale(chunk, _monotonic())

    def _stale(self, data: bytes, now: float) -> None:
        self._discard("stale", len(data))
        self._last_rx = now
        log.debug("stale input dropped: %s", data.hex(" "))

    def _events(self) -> Iterator[_Event]:
        framer = self._framer
        while (ev := framer.next_event()) is not None:
            error = ev.error
            yield (error.value if error else None, ev.message, len(ev.wire))

    def _exchange(
        self, slave: int, request: bytes, decode: Decoder[T] | None, expect: int
    ) -> T | None:
        """One attempt: send ``request`` to ``slave`` and return the decoded answer.

        ``expect``: the length of the answer's ADU when the request fixes it (RTU), for
        the fast path: an answer that arrives whole in one read, with its CRC, is taken
        without the framer (which would frame those bytes identically)."""
        fc = request[0]
        adu = self._encode(slave, request)
        port = self.port
        counters = self._counters
        rtu = self.mode == "rtu"
        self._before_send()
        framer = self._framer
        fed = False  # the framer is reset and told of the request when it gets bytes
        start, end = port.write(adu)
        self._tx_end = end
        counters["requests"] += 1
        debug = log.isEnabledFor(logging.DEBUG)
        if debug:
            log.debug(
                "TX slave %d fc %d: %s (%.3f ms on the line)",
                slave,
                fc,
                adu.hex(" "),
                (end - start) * 1e3,
            )
        echo = adu if self.echo else b""
        chunk = b""
        if decode is None:
            counters["broadcasts"] += 1
            self._quiet_until = end + self.broadcast_delay
            if echo:
                self._read_echo(slave, fc, adu, chunk, end + self.timeout)
            return None
        deadline = limit = end + self.timeout
        bad: FrameError | None = None
        fresh = rtu and expect > 0
        while True:
            now = _monotonic()
            if not chunk:
                wait = limit - now
                timer = framer.timer() if fed else None
                if timer is not None and timer - now < wait:
                    wait = timer - now
                chunk = port.read(wait)
                now = _monotonic()
            if chunk:
                self._last_rx = now
                if echo:
                    chunk, echo = self._eat_echo(slave, fc, adu, chunk, echo)
            if chunk:
                if fresh:
                    fresh = False
                    if chunk[0] == slave and self._check_crc(chunk):
                        if chunk[1] == fc and len(chunk) == expect:
                            if debug:
                                log.debug(
                                    "RX slave %d fc %d: %s (%.3f ms)",
                                    slave,
                                    fc,
                                    chunk.hex(" "),
                                    (now - end) * 1e3,
                                )
                            # malformed data: the framer path below reports it
                            with contextlib.suppress(FrameError):
                                value = decode(chunk[1:-2])
                                counters["responses"] += 1
                                return value
                        elif chunk[1] == fc | 0x80 and len(chunk) == 5:
                            counters["exceptions"] += 1
                            raise ExceptionResponseError(slave, fc, chunk[2])
                if not fed:
                    fed = True
                    framer.reset()
                    if rtu:
                        framer.send(adu)
                framer.receive_data(chunk, now)
                chunk = b""
                if bad is not None:
                    limit = min(deadline, now + self._settle)
            if not fed:
                if now >= limit:
                    break
                continue
            timer = framer.timer()
            if timer is not None and now >= timer:
                framer.handle_timer(now)
            for reason, message, size in self._events():
                if reason is not None:
                    self._discard(reason, size)
                    if reason == "crc":
                        counters["crc_errors"] += 1
                    bad = bad or FrameError(
                        f"{_name(fc)}: slave {slave}: {size} bytes discarded ({reason})", slave, fc
                    )
                elif message[0] != slave or message[1] & 0x7F != fc:
                    self._discard("unexpected", size)
                    if debug:
                        log.debug("RX dropped (not the answer): %s", message.hex(" "))
                    bad = bad or FrameError(
                        f"{_name(fc)}: slave {slave}: got a frame from slave {message[0]} "
                        f"function 0x{message[1]:02X} instead of the answer",
                        slave,
                        fc,
                    )
                else:
                    if debug:
                        log.debug(
                            "RX slave %d fc %d: %s (%.3f ms)",
                            slave,
                            fc,
                            message.hex(" "),
                            (now - end) * 1e3,
                        )
                    if message[1] & 0x80:
                        counters["exceptions"] += 1
                        raise ExceptionResponseError(
                            slave, fc, message[2] if len(message) > 2 else 0
                        )
                    try:
                        value = decode(message[1:])
                    except FrameError as exc:
                        self._discard("unexpected", size)
                        bad = bad or FrameError(f"slave {slave}: {exc}", slave, fc)
                    else:
                        counters["responses"] += 1
                        return value
                limit = min(deadline, now + self._settle)
            if now >= limit:
                break
        self._failed_at = _monotonic()
        if echo:
            counters["echo_mismatches"] += 1
            raise BusFault(
                f"{_name(fc)}: slave {slave}: the echo of the request did not come back", slave, fc
            )
        if bad is not None:
            counters["frame_errors"] += 1
            raise bad
        counters["timeouts"] += 1
        raise NoResponseError(
            f"{_name(fc)}: slave {slave}: no response within {self.timeout} s", slave, fc
        )

    def _eat_echo(
        self, slave: int, fc: int, adu: bytes, chunk: bytes, expected: bytes
    ) -> tuple[bytes, bytes]:
        """Match ``chunk`` against the echo still expected; the rest follows the echo."""
        n = min(len(chunk), len(expected))
        if chunk[:n] != expected[:n]:
            self._counters["echo_mismatches"] += 1
            self._let_settle()
            self._failed_at = _monotonic()
            got = adu[: len(adu) - len(expected)] + chunk[:n]
            raise BusFault(
                f"{_name(fc)}: slave {slave}: echo mismatch: "
                f"sent {adu.hex(' ')}, read back {got.hex(' ')}",
                slave,
                fc,
            )
        return chunk[n:], expected[n:]

    def _read_echo(self, slave: int, fc: int, adu: bytes, chunk: bytes, deadline: float) -> None:
        """A broadcast's echo: read back and verify the whole request."""
        expected = adu
        while True:
            if chunk:
                self._last_rx = _monotonic()
                rest, expected = self._eat_echo(slave, fc, adu, chunk, expected)
                if rest:
                    self._stale(rest, self._last_rx)
            if not expected:
                return
            wait = deadline - _monotonic()
            if wait <= 0:
                self._counters["echo_mismatches"] += 1
                raise BusFault(
                    f"{_name(fc)}: slave {slave}: the echo of the request did not come back",
                    slave,
                    fc,
                )
            chunk = self.port.read(wait)

    def _transact(
        self, slave: int, request: bytes, decode: Decoder[T] | None, expect: int = 0
    ) -> T | None:
        with self._lock:
            if self.port.closed:
                raise PortError(self.port.name, "the master is closed")
            attempt = 0
            while True:
                try:
                    return self._exchange(slave, request, decode, expect)
                except (NoResponseError, FrameError) as exc:
                    if attempt >= self.retries:
                        raise
                    attempt += 1
                    self._counters["retries"] += 1
                    log.debug("retry %d of %d after: %s", attempt, self.retries, exc)

    def _call(self, slave: int, request: bytes, decode: Decoder[T], expect: int = 0) -> T:
        """A transaction that must be answered (slave already checked, not 0)."""
        return self._transact(slave, request, decode, expect)  # type: ignore[return-value]

    def _write(self, slave: int, request: bytes, decode: Decoder[None], expect: int) -> None:
        """A write: broadcast (slave 0) awaits no answer."""
        self._transact(slave, request, None if slave == 0 else decode, expect)
