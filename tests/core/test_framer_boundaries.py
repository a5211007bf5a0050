"""The framer's silences exactly at t1.5 and t3.5, and one microsecond either side
(both backends, and the C core against its twin).

Modbus over Serial Line V1.02 §2.5.1.1: a silence of *at least* 3.5 character times
ends a frame; a silence of *more than* 1.5 character times between the characters of
one frame makes it an error.  So a silence of exactly t3.5 ends the frame, one of
exactly t1.5 does not spoil it.

The framer takes times in seconds and works in whole microseconds (`time_us` rounds);
every time here is a whole number of microseconds, checked to survive that rounding,
so the silences are exact.  A byte handed over alone at ``now`` arrived then (the end
of its character); the silence before it is ``now - char - previous arrival``.  The
expected t1.5 and t3.5 come from the spec's arithmetic, not from the code under test:
1.5 and 3.5 character times (11 bits, or 10 without parity) rounded to the
microsecond, and 750 / 1750 us above 19200 baud.
"""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu import ErrorReason, FrameKind

REQ = bytes.fromhex("010300000002")  # read 2 holding registers of slave 1: 8 bytes with CRC
VENDOR = bytes.fromhex("07550102030405")  # a function code without a length rule
T0_US = 1_000_000  # 1.0 s
CUT = 3  # the request is split after its third byte

#: (baudrate, parity) -> (char, t1.5, t3.5) in us, from the spec's arithmetic
LINES = {
    (9600, "E"): (round(11e6 / 9600), round(1.5 * 11e6 / 9600), round(3.5 * 11e6 / 9600)),
    (19200, "N"): (round(10e6 / 19200), round(1.5 * 10e6 / 19200), round(3.5 * 10e6 / 19200)),
    (115200, "E"): (round(11e6 / 115200), 750, 1750),  # fixed above 19200 baud
}


def seconds(us: int) -> float:
    """``us`` microseconds in seconds, such that the framer's rounding gives ``us`` back."""
    s = us / 1e6
    assert round(s * 1_000_000) == us
    return s


def spec(baud: int, parity: str) -> tuple[int, int, int]:
    return LINES[(baud, parity)]


def gaps_around(baud: int, parity: str) -> list[tuple[int, str]]:
    """Silences (us) at t1.5 and t3.5 and one microsecond either side, with the spec's
    verdict: ``frame`` (one good frame), ``t1.5`` (an error), ``split`` (two frames)."""
    _char, t15, t35 = spec(baud, parity)
    return [
        (t15 - 1, "frame"),
        (t15, "frame"),  # not *more than* 1.5 characters
        (t15 + 1, "t1.5"),
        (t35 - 1, "t1.5"),
        (t35, "split"),  # *at least* 3.5 characters
        (t35 + 1, "split"),
    ]


CASES = [
    (baud, parity, gap, verdict)
    for baud, parity in LINES
    for gap, verdict in gaps_around(baud, parity)
]
IDS = [f"{baud}{parity}-gap{gap}us-{verdict}" for baud, parity, gap, verdict in CASES]


def byte_times(baud: int, parity: str, length: int, gap_us: int) -> list[int]:
    """Arrival times (us) of ``length`` bytes back to back, with a silence of ``gap_us``
    before byte ``CUT``."""
    char, _t15, _t35 = spec(baud, parity)
    times = [T0_US + i * char for i in range(CUT)]
    times.append(times[-1] + char + gap_us)
    while len(times) < length:
        times.append(times[-1] + char)
    return times


def framed(backend: ModuleType, baud: int, parity: str, gap_us: int) -> list[tuple[object, ...]]:
    """The strict framer's events for the request fed one byte at a time."""
    adu = bytes(backend.add_crc(REQ))
    f = backend.Framer("slave", baudrate=baud, parity=parity, strict=True)
    for b, t in zip(adu, byte_times(baud, parity, len(adu), gap_us), strict=True):
        f.receive_data(bytes((b,)), seconds(t))
    f.handle_timer(10.0)
    return [(e.error, e.adu, e.start, e.end) for e in f.events()]


def check_verdict(
    events: list[tuple[object, ...]], adu: bytes, verdict: str, *, bulk: bool = False
) -> None:
    """``bulk``: the bulk parser, which reports a frame cut by a silence as one
    truncated run (the framer: the cut head, truncated, and the tail on its own)."""
    errors = [e[0] for e in events]
    assert b"".join(e[1] for e in events) == adu, events  # type: ignore[misc]
    if verdict == "frame":
        assert errors == [None], events
    elif verdict == "t1.5":
        assert errors[0] == ErrorReason.T15 and None not in errors, events
    elif bulk:
        assert errors == [ErrorReason.TRUNCATED], events
    else:  # the silence ended the head: cut short; the tail starts with function 0
        assert errors == [ErrorReason.TRUNCATED, ErrorReason.UNKNOWN_FUNCTION], events
        assert [e[1] for e in events] == [adu[:CUT], adu[CUT:]]


@pytest.mark.parametrize(("baud", "parity", "gap", "verdict"), CASES, ids=IDS)
def test_framer_silence_at_the_boundaries(
    backend: ModuleType, baud: int, parity: str, gap: int, verdict: str
) -> None:
    check_verdict(framed(backend, baud, parity, gap), bytes(backend.add_crc(REQ)), verdict)


@pytest.mark.parametrize(("baud", "parity", "gap", "verdict"), CASES, ids=IDS)
def test_parse_stream_silence_at_the_boundaries(
    backend: ModuleType, baud: int, parity: str, gap: int, verdict: str
) -> None:
    """The bulk parser marks silences by the same rule (csrc/rtu_stream.c)."""
    adu = bytes(backend.add_crc(REQ))
    times = [seconds(t) for t in byte_times(baud, parity, len(adu), gap)]
    result = backend.parse_stream(
        adu, "slave", times=times, baudrate=baud, parity=parity, strict=True
    )
    check_verdict([(f.error, f.adu, f.start, f.end) for f in result], adu, verdict, bulk=True)
    # the same bytes in two chunks: the first CUT bytes, then the rest
    chunks = [(0, times[CUT - 1]), (CUT, times[-1])]
    result = backend.parse_stream(
        adu, "slave", chunks=chunks, baudrate=baud, parity=parity, strict=True
    )
    check_verdict([(f.error, f.adu, f.start, f.end) for f in result], adu, verdict, bulk=True)


@pytest.mark.parametrize(("baud", "parity"), list(LINES))
def test_timer_ends_a_frame_of_unknown_length_at_exactly_t35(
    backend: ModuleType, baud: int, parity: str
) -> None:
    """A frame no length rule ends is ended by the timer at t3.5 after its last byte's
    arrival: not one microsecond before (the timer's own silence has no character
    in it: nothing arrives)."""
    _char, _t15, t35 = spec(baud, parity)
    adu = bytes(backend.add_crc(VENDOR))
    for strict in (False, True):
        f = backend.Framer("slave", baudrate=baud, parity=parity, strict=strict)
        f.receive_data(adu, seconds(T0_US))
        assert f.timer() == pytest.approx(seconds(T0_US + t35), abs=1e-9)
        f.handle_timer(seconds(T0_US + t35 - 1))
        assert f.next_event() is None
        f.handle_timer(seconds(T0_US + t35))
        ev = f.next_event()
        assert ev is not None and ev.error is None and ev.adu == adu
        assert ev.kind == FrameKind.REQUEST


@pytest.mark.parametrize(("baud", "parity"), list(LINES))
def test_c_core_and_twin_agree_at_the_boundaries(
    both: tuple[ModuleType, ModuleType], baud: int, parity: str
) -> None:
    """Every silence from t1.5 - 2 to t1.5 + 2 and t3.5 - 2 to t3.5 + 2 us: the same
    events (errors, bytes, times) from the C core and the twin, by feed and by the
    bulk parser, strict and lenient."""
    c, py = both
    _char, t15, t35 = spec(baud, parity)
    for gap in [*range(t15 - 2, t15 + 3), *range(t35 - 2, t35 + 3)]:
        assert framed(c, baud, parity, gap) == framed(py, baud, parity, gap), gap
        adu = bytes(c.add_crc(REQ))
        times = [seconds(t) for t in byte_times(baud, parity, len(adu), gap)]
        for strict in (False, True):
            got = [
                [
                    (f.error, f.adu, f.start, f.end)
                    for f in b.parse_stream(
                        adu, "slave", times=times, baudrate=baud, parity=parity, strict=strict
                    )
                ]
                for b in (c, py)
            ]
            assert got[0] == got[1], (gap, strict)
