"""Property tests: the C core and the pure-Python twin agree on random input."""

from __future__ import annotations

import array
from collections.abc import Callable, Iterable
from fractions import Fraction
from types import ModuleType
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pyrtu import BONFIGLIOLI

SETTINGS = settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


def _frames(b: ModuleType) -> st.SearchStrategy[bytes]:
    """Plausible frames (valid CRC), noise, and frames with a flipped bit."""
    pdus = st.sampled_from(
        [
            "0103000a0002",
            "01030401020304",
            "0206000100ff",
            "0a10000100020400010002",
            "0a1000010002",
            "05830200",
            "0b0f00000010020f00",
            "0b01020f00",
            "07550102",
            "01640001",
            "016400000001",
            "01650001000000020",
            "002b0e0100",
            "012b0e01010000010003414243",
            "030800000000",
            "0117000000020000000102000a",
        ]
    ).map(lambda h: bytes.fromhex(h if len(h) % 2 == 0 else h + "0"))
    good = pdus.map(b.add_crc)
    noise = st.binary(min_size=1, max_size=12)
    flipped = st.tuples(good, st.integers(0, 10_000)).map(
        lambda gf: bytes(
            x ^ (1 << (gf[1] % 8)) if i == (gf[1] // 8) % len(gf[0]) else x
            for i, x in enumerate(gf[0])
        )
    )
    return st.one_of(good, good, noise, flipped)


@st.composite
def streams(draw: st.DrawFn, b: ModuleType) -> tuple[bytes, list[tuple[int, float]]]:
    parts = draw(st.lists(_frames(b), min_size=1, max_size=12))
    data = b"".join(parts)
    # chunk boundaries with random gaps (0 to 20 ms) at 19200 baud
    cuts = sorted(set(draw(st.lists(st.integers(1, max(1, len(data) - 1)), max_size=10))))
    offsets = [0] + [c for c in cuts if c < len(data)]
    t = 1.0
    chunks = []
    for o in offsets:
        t += draw(st.sampled_from([0.0, 0.0002, 0.0008, 0.0012, 0.0025, 0.016, 0.1]))
        chunks.append((o, t))
    return data, chunks


def _events(
    mod: ModuleType, data: bytes, chunks: list[tuple[int, float]], **kw: object
) -> list[tuple[object, ...]]:
    f = mod.Framer(**kw)
    bounds = [o for o, _ in chunks] + [len(data)]
    for (o, t), end in zip(chunks, bounds[1:], strict=True):
        f.receive_data(data[o:end], t)
        deadline = f.timer()
        if deadline is not None and deadline < t + 0.0001:
            f.handle_timer(deadline)
    f.handle_timer(chunks[-1][1] + 10.0)
    out = [(e.kind, e.adu, e.offset, e.error, e.start, e.end) for e in f.events()]
    out.append(tuple(sorted(f.counters.items())))
    return out


def _bulk(
    mod: ModuleType, data: bytes, chunks: list[tuple[int, float]] | None, **kw: object
) -> list[tuple[object, ...]]:
    r = mod.parse_stream(data, chunks=chunks, **kw)
    out = [(e.kind, e.adu, e.offset, e.error, e.start, e.end) for e in r]
    out.append(tuple(sorted(r.counters.items())))
    return out


@given(data=st.data())
@SETTINGS
def test_crc_and_lrc_agree(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    c, py = both
    raw = data.draw(st.binary(max_size=600))
    seed = data.draw(st.integers(0, 0xFFFF))
    assert c.crc16(raw, seed) == py.crc16(raw, seed)
    assert c.lrc(raw) == py.lrc(raw)
    assert c.check_crc(raw) == py.check_crc(raw)
    assert c.add_crc(raw) == py.add_crc(raw)


@given(data=st.data())
@SETTINGS
def test_timing_agrees(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    c, py = both
    baud = data.draw(st.integers(50, 4_000_000))
    parity = data.draw(st.sampled_from("NEO"))
    stop = data.draw(st.sampled_from([1, 2]))
    rule = data.draw(st.sampled_from(["modbus", "weg"]))
    assert c.char_timing(baud, parity, stop, timing=rule) == py.char_timing(
        baud, parity, stop, timing=rule
    )


@given(data=st.data())
@SETTINGS
def test_framer_agrees_on_random_streams(
    both: tuple[ModuleType, ModuleType], data: st.DataObject
) -> None:
    c, py = both
    stream, chunks = data.draw(streams(c))
    role = data.draw(st.sampled_from(["master", "slave", "monitor"]))
    strict = data.draw(st.booleans())
    max_adu = data.draw(st.sampled_from([64, 256]))
    kw = {"role": role, "strict": strict, "max_adu": max_adu, "rules": BONFIGLIOLI}
    got_c = _events(c, stream, chunks, **kw)
    assert got_c == _events(py, stream, chunks, **kw)
    for _kind, adu, _o, error, *_ in got_c[:-1]:
        if error is None:
            assert c.check_crc(adu), "a frame with a bad CRC was returned"


@given(data=st.data())
@SETTINGS
def test_parse_stream_agrees(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    c, py = both
    stream, chunks = data.draw(streams(c))
    role = data.draw(st.sampled_from(["master", "slave", "monitor"]))
    strict = data.draw(st.booleans())
    timed = data.draw(st.booleans())
    kw = {"role": role, "strict": strict, "rules": BONFIGLIOLI}
    got = _bulk(c, stream, chunks if timed else None, **kw)
    assert got == _bulk(py, stream, chunks if timed else None, **kw)
    assert sum(len(e[1]) for e in got[:-1]) == len(stream)  # every byte accounted for


# ---- hostile input: the same result or the same exception type -----------------

HOSTILE_SETTINGS = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


def _outcome(fn: Callable[[], object]) -> tuple[str, object]:
    """("ok", result) or ("raise", exception type); NaN-free results compare with ==."""
    try:
        return ("ok", fn())
    except Exception as exc:
        return ("raise", type(exc))


def _agree(c: ModuleType, py: ModuleType, fn: Callable[[ModuleType], object]) -> tuple[str, object]:
    got_c = _outcome(lambda: fn(c))
    got_py = _outcome(lambda: fn(py))
    assert got_c == got_py
    return got_c


def _released(raw: bytes) -> memoryview:
    view = memoryview(raw)
    view.release()
    return view


#: The same bytes in many buffer shapes, and things that are not buffers.
BUFFER_SHAPES: list[Callable[[bytes], object]] = [
    lambda raw: raw,
    bytearray,
    memoryview,
    lambda raw: memoryview(raw)[::2],
    lambda raw: memoryview(raw)[::-1],
    lambda raw: memoryview(raw)[1::3],
    lambda raw: array.array("B", raw),
    lambda raw: array.array("H", raw[: len(raw) // 2 * 2]),
    lambda raw: memoryview(array.array("H", raw[: len(raw) // 4 * 4]))[::2],
    lambda raw: memoryview(raw[: len(raw) // 2 * 2]).cast("B", (2, len(raw) // 2)),
    _released,
    lambda raw: raw.hex(),
    list,
    len,
    lambda raw: None,
]


def _events_of(r: Iterable[Any]) -> list[tuple[object, ...]]:
    return [(e.kind, e.adu, e.offset, e.error, e.start, e.end) for e in r]


@given(data=st.data())
@HOSTILE_SETTINGS
def test_buffers_agree(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    """Strided, reversed, multi-dimensional, released and non-buffers: C copies what the
    twin reads (issue 9: crc16 of memoryview(b'abcdef')[::2] raised BufferError in C)."""
    c, py = both
    raw = data.draw(st.binary(min_size=2, max_size=80))
    buf = BUFFER_SHAPES[data.draw(st.integers(0, len(BUFFER_SHAPES) - 1))](raw)
    seed = data.draw(st.sampled_from([0xFFFF, 0, 0x1234, -1, 0x10000, True, 1.0, "1", None]))
    _agree(c, py, lambda b: b.crc16(buf, seed))
    _agree(c, py, lambda b: b.crc16(buf))
    _agree(c, py, lambda b: b.lrc(buf))
    _agree(c, py, lambda b: b.check_crc(buf))
    _agree(c, py, lambda b: b.add_crc(buf))
    _agree(c, py, lambda b: b.crc16_path("bytewise", buf))
    got = _agree(c, py, lambda b: _events_of(b.parse_stream(buf)))
    _agree(c, py, lambda b: b.Framer().receive_data(buf, 1.0))
    _agree(c, py, lambda b: b.Framer().send(buf))
    if isinstance(buf, memoryview | bytearray | array.array) and got[0] == "ok":
        # a buffer is read as its bytes in logical order
        assert got == ("ok", _events_of(c.parse_stream(memoryview(buf).tobytes())))
    if not isinstance(buf, bytes | bytearray | memoryview | array.array):
        assert got == ("raise", TypeError)


EXTREME_TIMES = [
    0.0,
    -1.0,
    1e-7,
    1e300,
    -1e300,
    float("nan"),
    float("inf"),
    -float("inf"),
    9.2e12,
    -9.2e12,
    9223372036854.775,
    -9223372036854.775,
    9223372036854.776,
    2**53,
    10**30,
    True,
    "1",
    None,
    Fraction(1, 3),
]


def _times(n_min: int = 0) -> st.SearchStrategy[object]:
    return st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.floats(min_value=-1e13, max_value=1e13),
        st.integers(min_value=-(10**14), max_value=10**14),
        st.sampled_from(EXTREME_TIMES),
    )


@given(data=st.data())
@HOSTILE_SETTINGS
def test_hostile_times_agree(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    """Huge, negative, non-monotonic, NaN, infinite and non-number times: per-byte,
    per-chunk and in the framer (issue 9: chunks=[(0, 0.0), (8, 1e300)] raised
    OverflowError in C only; int64 arithmetic wrapped in the core)."""
    c, py = both
    stream, _ = data.draw(streams(c))
    n = len(stream)
    strict = data.draw(st.booleans())
    role = data.draw(st.sampled_from(["master", "slave", "monitor"]))
    kw = {"role": role, "strict": strict}
    # per-byte times: mostly sane steps with hostile values mixed in
    base = data.draw(st.sampled_from([0.0, 9.2e12, -9.2e12, 1.0]))
    times = [base + i * 0.0006 for i in range(n)]
    for _ in range(data.draw(st.integers(0, 3))):
        times[data.draw(st.integers(0, n - 1))] = data.draw(_times())  # type: ignore[call-overload]
    got = _agree(c, py, lambda b: _events_of(b.parse_stream(stream, times=times, **kw)))
    if got[0] == "raise":
        assert got[1] in (TypeError, ValueError)
    # chunks with hostile times, ascending offsets
    cuts = sorted(set(data.draw(st.lists(st.integers(0, n), max_size=6))) | {0})
    chunks = [(o, data.draw(_times())) for o in cuts]
    got = _agree(c, py, lambda b: _events_of(b.parse_stream(stream, chunks=chunks, **kw)))
    if got[0] == "raise":
        assert got[1] in (TypeError, ValueError)

    # the framer: receive_data / handle_timer / timer at hostile times
    def run(b: ModuleType) -> list[object]:
        f = b.Framer(role, strict=strict)
        out: list[object] = []
        pos = 0
        for o in [*cuts[1:], n]:
            piece = stream[pos:o]
            out.append(_outcome(lambda p=piece: f.receive_data(p, data_times.pop())))  # type: ignore[misc]
            out.append(_outcome(f.timer))
            out.append(_outcome(lambda: f.handle_timer(data_times.pop())))
            pos = o
        out.append(_events_of(f.events()))
        out.append(sorted(f.counters.items()))
        return out

    draws = [data.draw(_times()) for _ in range(2 * len(cuts) + 2)]
    data_times = list(draws)
    got_c = run(c)
    data_times = list(draws)
    assert got_c == run(py)


@given(data=st.data())
@HOSTILE_SETTINGS
def test_weird_chunk_tables_agree(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    """Malformed chunk tables give the same clear exception on both backends, a TypeError
    or ValueError naming chunks (issue 9: [(0,)] and [(0, 'x')] gave raw texts)."""
    c, py = both
    stream = data.draw(st.binary(min_size=0, max_size=30))
    entry = st.one_of(
        st.tuples(st.integers(-2, 40), st.floats(0, 10)),
        st.tuples(st.integers(0, 40)),
        st.tuples(st.integers(0, 40), st.floats(0, 10), st.floats(0, 10)),
        st.tuples(st.sampled_from([0.0, 1.5, "0", None, True, b"0"]), st.floats(0, 10)),
        st.tuples(st.integers(0, 40), st.sampled_from(["x", None, b"", [1], float("nan")])),
        st.sampled_from([0, "ab", None, b"\x00\x01", (), [0, 1.0]]),
    )
    chunks = data.draw(
        st.one_of(
            st.lists(entry, max_size=5),
            st.sampled_from([5, "chunks", b"\x00", None, 1.5]),
        )
    )
    got = _agree(c, py, lambda b: _events_of(b.parse_stream(stream, chunks=chunks)))
    if got[0] == "raise":
        assert got[1] in (TypeError, ValueError)
        with pytest.raises(got[1], match="chunks"):  # the message names the argument
            c.parse_stream(stream, chunks=chunks)
    times = data.draw(st.sampled_from([[0.0] * len(stream), "x" * len(stream), 7, [None], []]))
    got = _agree(c, py, lambda b: _events_of(b.parse_stream(stream, times=times)))
    if got[0] == "raise":
        assert got[1] in (TypeError, ValueError)
        with pytest.raises(got[1], match="times"):
            c.parse_stream(stream, times=times)


BAD_KEYWORDS: dict[str, list[object]] = {
    "baudrate": [0, -1, 1, 50, 2**31, 2**32, 2**40, 30_000_000, 9_999_999, "19200", 1.5, True],
    "t15": [0, 1e-6, 0.01, -1.0, float("nan"), float("inf"), 1e13, 9e12, 1e300, "x", True],
    "t35": [0, 1e-6, 0.01, -1.0, float("nan"), float("inf"), 1e13, 9e12, 1e300, "x", True],
    "max_adu": [3, 4, 1024, 1025, 256.0, True, "256", -1],
    "strict": [True, False, 0, 1],
    "timing": ["modbus", "weg", "WEG", 1, None],
    "stopbits": [1, 2, 1.5, 3, 0],
    "bytesize": [7, 8, 9],
    "role": ["master", "monitor", "Monitor", 1, None],
}


@given(data=st.data())
@HOSTILE_SETTINGS
def test_bad_keywords_agree(both: tuple[ModuleType, ModuleType], data: st.DataObject) -> None:
    """Out-of-range and wrong-type keyword values (issue 9: baud rates past 32 bits, t3.5
    past int64 microseconds, raised OverflowError in C only)."""
    c, py = both
    names = data.draw(st.lists(st.sampled_from(sorted(BAD_KEYWORDS)), max_size=3, unique=True))
    kw = {name: data.draw(st.sampled_from(BAD_KEYWORDS[name])) for name in names}
    frame = c.add_crc(bytes.fromhex("0103000a0002"))
    stream = b"\x00" + frame + frame
    chunks = [(0, 1.0), (5, 1.01)]
    _agree(c, py, lambda b: _events_of(b.parse_stream(stream, chunks=chunks, **kw)))
    framer_kw = dict(kw)
    if data.draw(st.booleans()):
        framer_kw["flush_timeout"] = data.draw(st.sampled_from([0.0, 1.0, 1e13, 1e300, -1.0]))

    def framer(b: ModuleType) -> object:
        f = b.Framer(**framer_kw)
        f.receive_data(stream, 1.0)
        return (_events_of(f.events()), f.timer())

    _agree(c, py, framer)
    timing_kw = {
        k: v for k, v in kw.items() if k in ("stopbits", "bytesize", "timing", "t15", "t35")
    }
    _agree(c, py, lambda b: b.char_timing(kw.get("baudrate", 19200), **timing_kw))
