"""The Python face of the framer and of parse_stream, shared by both backends.

A backend supplies a *core*: ``feed(data, now_us) -> int``, ``poll() -> event``,
``handle_timer(now_us)``, ``deadline() -> int | None``, ``sent(adu)``,
``reset()`` and ``counts() -> (frames[4], discarded[6], discard_events)``.
"""

from __future__ import annotations

import numbers
import operator
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Generic, NamedTuple, Protocol, TypeVar

from pyrtu.core._types import BytesLike
from pyrtu.core.feed import feed_all
from pyrtu.core.frames import (
    ERROR_BY_CODE,
    Frame,
    FrameKind,
    FrameList,
    event_counters_template,
    make_frame,
)
from pyrtu.core.line import FormatKeywords, FramerKeywords, LineConfig, check_keywords, line_from
from pyrtu.core.options import CoreOptions, core_options, to_microseconds
from pyrtu.core.timing import TIMING_RULES, Timing, compute_timing

if TYPE_CHECKING:  # Unpack is in typing from Python 3.11 (annotations only)
    from typing import Unpack

# (offset, length, kind, error, start_us, end_us, adu)
Event = tuple[int, int, int, int, int, int, bytes]

#: a backend's ``request_predictor(options)(adu) -> (status, length)`` statuses:
#: rtu_predict's RTU_PRED_* (csrc/rtu.h), the same in the twin
PRED_LENGTH = 0  # length is the ADU's length
PRED_NEED = 1  # more bytes needed; length is how many to decide
PRED_UNKNOWN = 2  # no rule for this function


class FramerCore(Protocol):
    def feed(self, data: bytes, now_us: int) -> int: ...
    def poll(self) -> Event | None: ...
    def handle_timer(self, now_us: int) -> None: ...
    def deadline(self) -> int | None: ...
    def sent(self, adu: bytes) -> None: ...
    def reset(self) -> None: ...
    def needed(self) -> int: ...
    def expect(self, adu: bytes) -> None: ...
    def take(self) -> tuple[int, int, bytes] | None: ...
    def counts(self) -> tuple[Sequence[int], Sequence[int], int]: ...


E = TypeVar("E")


class EventQueue(Generic[E]):
    """The events a framer made and its owner has not taken yet (h11's next_event)."""

    _events: deque[E]

    def next_event(self) -> E | None:
        """The next frame or discard event, or None when there is none yet."""
        return self._events.popleft() if self._events else None

    def events(self) -> list[E]:
        """All events available now."""
        out = list(self._events)
        self._events.clear()
        return out


def as_bytes(data: BytesLike, name: str = "data") -> bytes:
    """Any buffer (strided or multi-dimensional ones too, in logical order) as bytes."""
    if isinstance(data, bytes):
        return data
    try:
        view = memoryview(data)
    except TypeError:
        raise TypeError(f"{name} must be a bytes-like object, not {type(data).__name__}") from None
    return view.tobytes()


INT64_MAX = 2**63 - 1
#: Times and durations reach the C core as int64 microseconds; INT64_MIN is its
#: "no time", so both backends accept |t| <= INT64_MAX us (about 292,000 years).
MAX_SECONDS = INT64_MAX / 1e6


def time_us(value: object, name: str, index: int = 0) -> int:
    """A time in seconds (a real number) as integer microseconds, checked the same way
    for both backends: TypeError for a non-number, ValueError for NaN, infinities and
    times beyond +-INT64_MAX microseconds.  ``name`` may hold ``{}`` for ``index``
    (formatted only for an error message: this runs once per chunk)."""
    kind = type(value)
    if kind is float:  # the common case first: NaN and infinities fail the comparison
        if -MAX_SECONDS <= value <= MAX_SECONDS:  # type: ignore[operator]
            us = round(value * 1_000_000)  # type: ignore[operator]
            if -INT64_MAX <= us <= INT64_MAX:
                return us
    elif kind is bool or not isinstance(value, numbers.Real):
        raise TypeError(
            f"{name.format(index)} must be a number of seconds, not {type(value).__name__}"
        )
    else:
        try:
            us = to_microseconds(value if isinstance(value, int) else float(value))
        except (ValueError, OverflowError):
            us = INT64_MAX + 1
        if -INT64_MAX <= us <= INT64_MAX:
            return us
    raise ValueError(
        f"{name.format(index)} must be a finite time within +-{MAX_SECONDS:.3g} s, not {value!r}"
    )


def check_core_limits(options: CoreOptions) -> None:
    """What the C core's int64/uint32 fields and its 1 us resolution impose, checked
    before either backend builds its configuration (ValueError naming the argument)."""
    for name, us in (
        ("t15", options.t15_us),
        ("t35", options.t35_us),
        ("flush_timeout", options.flush_us),
    ):
        if us is not None and us > INT64_MAX:
            raise ValueError(f"{name} must be at most {MAX_SECONDS:.3g} s, not {us / 1e6:g} s")
    timing = compute_timing(options.baudrate, options.bits, TIMING_RULES[options.rule])
    if options.baudrate > 0xFFFFFFFF or timing.char_us < 1:
        raise ValueError(
            f"baudrate {options.baudrate} is too high: a character would last under 1 us, "
            "the core's time resolution"
        )


def event_to_frame(ev: Event) -> Frame:
    offset, _length, kind, error, start_us, end_us, adu = ev
    return make_frame(kind, adu, offset, start_us / 1e6, end_us / 1e6, error)


def counters_dict(frames: Sequence[int], discarded: Sequence[int], events: int) -> dict[str, int]:
    out = event_counters_template()
    for kind in (FrameKind.REQUEST, FrameKind.RESPONSE, FrameKind.EXCEPTION, FrameKind.UNKNOWN):
        out[str(kind)] = int(frames[kind])
    for code, reason in enumerate(ERROR_BY_CODE):
        if reason is not None:
            out[f"discarded_{reason.value}"] = int(discarded[code])
    out["discard_events"] = int(events)
    return out


class FramerBase(EventQueue[Frame]):
    """A sans-I/O Modbus RTU connection (in the spirit of h11).

    Feed bytes with ``receive_data(data, now)`` (``now``: seconds on a monotonic
    clock), pull ``Frame`` events with ``next_event()`` until it returns None,
    and call ``handle_timer(now)`` when ``timer()`` says, so that silences end
    frames.  ``send(adu)`` tells the framer what the local side transmitted.
    """

    BACKEND = ""

    def __init__(
        self,
        role: str = "master",
        *,
        line: LineConfig | None = None,
        **keywords: Unpack[FramerKeywords],
    ) -> None:
        check_keywords(keywords, FramerKeywords.__optional_keys__, "Framer")
        if line is None:
            self.options = core_options(role, **keywords)
        else:
            line = line_from(line, "Framer", **keywords)  # (refuses line= with keywords)
            if line.mode != "rtu":
                raise ValueError(
                    "line: Framer frames RTU; for ASCII use pyrtu.core.ascii.make_framer(line)"
                )
            self.options = line.options(role)
        self.role = role
        self._core = self._make_core(self.options)
        self._events: deque[Frame] = deque()

    def _make_core(self, options: CoreOptions) -> FramerCore:
        raise NotImplementedError

    @property
    def core(self) -> FramerCore:
        """The core this framer drives: the feed/take interface the protocols use (the
        ASCII framer has one too, `pyrtu.core.ascii.AsciiCore`)."""
        return self._core

    def _drain(self) -> None:
        while (ev := self._core.poll()) is not None:
            self._events.append(event_to_frame(ev))

    def receive_data(self, data: BytesLike, now: float) -> None:
        """Bytes that arrived (were read) at ``now`` seconds."""
        raw = data if type(data) is bytes else as_bytes(data)
        now_us = time_us(now, "now")
        core = self._core
        # a silence before the new bytes may end what is buffered: events after each feed
        feed_all(lambda chunk: core.feed(chunk, now_us), raw, self._drain)

    def timer(self) -> float | None:
        """When ``handle_timer`` must run (seconds), or None when no timer is needed."""
        deadline = self._core.deadline()
        return None if deadline is None else deadline / 1e6

    def handle_timer(self, now: float) -> None:
        """Let the silence up to ``now`` end what it ends."""
        self._core.handle_timer(time_us(now, "now"))
        self._drain()

    def send(self, adu: BytesLike) -> bytes:
        """Record that ``adu`` is transmitted by this side; returns the bytes to write."""
        raw = as_bytes(adu, "adu")
        self._core.sent(raw)
        return raw

    def needed(self) -> int:
        """Bytes still needed: a lower bound on how many more bytes must arrive
        before the frame at the head can end by its predicted length, so a driver
        may sleep ``needed() x character time`` (with ``timer()`` as a safety net).

        Call it after ``next_event()`` returned None.  With bytes pending: the least,
        over the directions tried at the head, of the shortest frame the length
        rules allow for the bytes so far, minus the bytes pending (one pending
        byte: 1, or in the master role, when it is the awaited slave's address, the
        shortest answer minus 1).  Nothing pending: in the master role after
        ``send(request)`` the shortest answer (the response's shortest length, or 5
        for an exception response, whichever is less); otherwise 0.  0 also when no
        rule predicts the head (unknown function, length past ``max_adu``) or only a
        silence can end it: then wake on the next byte or the timer.  Same value
        from the C core (``rtu_framer_needed``) and the twin.
        """
        return self._core.needed()

    def restart(self, adu: bytes | None = None) -> None:
        """``reset()``, then ``send(adu)`` when given: a new transaction in one call."""
        core = self._core
        core.reset()
        self._events.clear()
        if adu is not None:
            core.sent(adu)

    def reset(self) -> None:
        """Drop buffered bytes (counted as truncated) and the request context."""
        self._core.reset()
        self._events.clear()

    @property
    def counters(self) -> dict[str, int]:
        """Frames by kind and discarded bytes by reason, since creation."""
        return counters_dict(*self._core.counts())


def stream_times(
    length: int,
    times: Iterable[float] | None,
    chunks: Iterable[tuple[int, float]] | None,
) -> tuple[list[int], list[int]]:
    """Chunk offsets and times (us) from per-byte ``times`` or ``chunks``, checked."""
    if times is not None and chunks is not None:
        raise ValueError("parse_stream: give times= or chunks=, not both")
    if times is not None:
        us = [
            time_us(t, "parse_stream: times[{}]", i)
            for i, t in enumerate(_iterable(times, "times"))
        ]
        if len(us) != length:
            raise ValueError(f"parse_stream: times has {len(us)} entries for {length} bytes")
        return list(range(length)), us
    if chunks is None:
        return [], []
    offsets: list[int] = []
    us = []
    for i, chunk in enumerate(_iterable(chunks, "chunks")):
        if type(chunk) is tuple and len(chunk) == 2 and type(chunk[0]) is int:
            offset, t = chunk  # the common case, checked below like any other
            if 0 <= offset <= length and (not offsets or offset >= offsets[-1]):
                offsets.append(offset)
                if type(t) is float and -9e12 < t < 9e12:  # well inside int64 us
                    us.append(round(t * 1_000_000))
                else:
                    us.append(time_us(t, "parse_stream: chunks[{}] time", i))
                continue
        raw_offset: object
        try:
            raw_offset, t = chunk  # type: ignore[misc]
        except (TypeError, ValueError):
            raise TypeError(
                f"parse_stream: chunks[{i}] must be an (offset, time) pair, not {chunk!r}"
            ) from None
        if isinstance(raw_offset, bool) or not hasattr(raw_offset, "__index__"):
            raise TypeError(
                f"parse_stream: chunks[{i}] offset must be an integer, "
                f"not {type(raw_offset).__name__}"
            )
        offset = operator.index(raw_offset)
        if offset < 0 or offset > length:
            raise ValueError(
                f"parse_stream: chunks[{i}] offset {offset} is outside the data (0..{length})"
            )
        if offsets and offset < offsets[-1]:
            raise ValueError(
                f"parse_stream: chunks offsets must ascend (chunks[{i}] at {offset} "
                f"after {offsets[-1]})"
            )
        offsets.append(offset)
        us.append(time_us(t, "parse_stream: chunks[{}] time", i))
    if offsets and offsets[0] != 0:
        raise ValueError(
            f"parse_stream: chunks[0], the first chunk, must start at offset 0, not {offsets[0]}"
        )
    return offsets, us


def _iterable(value: object, name: str) -> Iterable[object]:
    if isinstance(value, str | bytes) or not isinstance(value, Iterable):
        raise TypeError(f"parse_stream: {name} must be an iterable, not {type(value).__name__}")
    return value


class StreamParser(Protocol):
    def __call__(
        self, options: CoreOptions, data: bytes, offsets: list[int], times_us: list[int]
    ) -> FrameList: ...


F = TypeVar("F", bound=Callable[..., object])


def public(function: F) -> F:
    """Name a backend's function by its public path (``pyrtu.NAME``): the function a
    factory below makes is what ``pyrtu`` exports, and introspection (``help()``, the
    documentation's API reference) should say so, not ``make_...<locals>``."""
    function.__module__ = "pyrtu"
    function.__qualname__ = function.__name__
    return function


def make_parse_stream(parse: StreamParser) -> Callable[..., FrameList]:
    """The public parse_stream of a backend, around its ``parse(options, data, ...)``."""

    def parse_stream(
        data: BytesLike,
        role: str = "monitor",
        *,
        times: Iterable[float] | None = None,
        chunks: Iterable[tuple[int, float]] | None = None,
        line: LineConfig | None = None,
        **keywords: Unpack[FormatKeywords],
    ) -> FrameList:
        """Every frame and discard run in ``data`` (a capture), as a lazy sequence.

        ``times``: per-byte arrival times (seconds); ``chunks``: ``[(offset, time), ...]``,
        the bytes from ``offset`` to the next chunk arrived by ``time``.  Without either,
        only prediction and CRC split the stream.  The result's ``counters`` give frames by
        kind and discarded bytes by reason.  The line: the line keywords (baudrate,
        parity, stopbits, bytesize, timing, t15, t35, strict, max_adu, rules) or
        ``line``, a `LineConfig`.
        """
        check_keywords(keywords, FormatKeywords.__optional_keys__, "parse_stream")
        if line is not None:
            options = line_from(line, "parse_stream", **keywords).options(role)
        else:
            options = core_options(role, **keywords)
        raw = as_bytes(data)
        offsets, us = stream_times(len(raw), times, chunks)
        return parse(options, raw, offsets, us)

    return public(parse_stream)


def make_char_timing(compute: Callable[[CoreOptions], Timing]) -> Callable[..., Timing]:
    """The public char_timing of a backend, around its ``compute(options)``."""

    def char_timing(
        baudrate: int,
        parity: str = "E",
        stopbits: float = 1,
        bytesize: int = 8,
        timing: str = "modbus",
        t15: float | None = None,
        t35: float | None = None,
    ) -> Timing:
        """Character time, t1.5 and t3.5 for a baud rate and byte format."""
        options = core_options(
            "master",
            baudrate=baudrate,
            parity=parity,
            stopbits=stopbits,
            bytesize=bytesize,
            timing=timing,
            t15=t15,
            t35=t35,
        )
        return compute(options)

    return public(char_timing)


class FramingNames(NamedTuple):
    """The public RTU names of a backend (`backend_framing`)."""

    Framer: type[FramerBase]
    parse_stream: Callable[..., FrameList]
    char_timing: Callable[..., Timing]


def backend_framing(
    backend: str,
    make_core: Callable[[CoreOptions], FramerCore],
    parse: StreamParser,
    compute: Callable[[CoreOptions], Timing],
) -> FramingNames:
    """The public Framer class, parse_stream and char_timing of a backend, around its
    ``make_core(options)``, its ``parse(options, data, ...)`` and its ``compute(options)``."""

    class Framer(FramerBase):
        __doc__ = FramerBase.__doc__
        BACKEND = backend

        def _make_core(self, options: CoreOptions) -> FramerCore:
            return make_core(options)

    Framer.__qualname__ = Framer.__name__
    Framer.__module__ = make_core.__module__  # the backend's module
    return FramingNames(Framer, make_parse_stream(parse), make_char_timing(compute))
