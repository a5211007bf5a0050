"""Property tests: the C MBAP framer and its pure-Python twin agree on random input."""

from __future__ import annotations

import itertools
from types import ModuleType

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import pyrtu

SETTINGS = settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
ROLES = st.sampled_from(["master", "slave", "monitor"])


def _adu(tid: int, unit: int, body: bytes) -> bytes:
    n = len(body) + 1
    return bytes((tid >> 8, tid & 0xFF, 0, 0, n >> 8, n & 0xFF, unit)) + body


good = st.builds(
    _adu,
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFF),
    st.binary(min_size=1, max_size=253),
)
# a header byte changed: protocol id or length may break (or stay valid)
damaged = st.tuples(good, st.integers(0, 6), st.integers(0, 255)).map(
    lambda t: t[0][: t[1]] + bytes([t[2]]) + t[0][t[1] + 1 :]
)
noise = st.binary(min_size=1, max_size=16)


@st.composite
def streams(draw: st.DrawFn) -> tuple[bytes, list[int]]:
    parts = draw(st.lists(st.one_of(good, good, good, damaged, noise), min_size=1, max_size=8))
    data = b"".join(parts)
    cuts = sorted(set(draw(st.lists(st.integers(0, len(data)), max_size=12))))
    return data, cuts


def _run(mod: ModuleType, role: str, data: bytes, cuts: list[int], eof: bool) -> list[object]:
    f = mod.MbapFramer(role)
    out: list[object] = []
    bounds = [0, *cuts, len(data)]
    for a, b in itertools.pairwise(bounds):
        if a == b:
            continue
        f.receive_data(data[a:b])
        out.append([(e.kind, e.adu, e.offset, e.error) for e in f.events()])
        out.append((f.needed, f.error))
    if eof:
        f.receive_data(b"")
        out.append([(e.kind, e.adu, e.offset, e.error) for e in f.events()])
        out.append((f.needed, f.error))
    out.append(f.counters)
    return out


@SETTINGS
@given(stream=streams(), role=ROLES, eof=st.booleans())
def test_framer_agrees(
    both: tuple[ModuleType, ModuleType], stream: tuple[bytes, list[int]], role: str, eof: bool
) -> None:
    c, py = both
    data, cuts = stream
    assert _run(c, role, data, cuts, eof) == _run(py, role, data, cuts, eof)


@SETTINGS
@given(stream=streams(), role=ROLES)
def test_parse_tcp_stream_agrees_and_matches_the_framer(
    both: tuple[ModuleType, ModuleType], stream: tuple[bytes, list[int]], role: str
) -> None:
    c, py = both
    data, cuts = stream
    got = {}
    for mod in (c, py):
        result = mod.parse_tcp_stream(data, role)
        got[mod.BACKEND] = ([(e.kind, e.adu, e.offset, e.error) for e in result], result.counters)
    assert got["c"] == got["python"]
    entries = got["c"][0]
    assert sum(len(e[1]) for e in entries) == len(data)  # every byte accounted for once
    # the framer, fed in pieces and closed, finds the same ADUs and the same first error
    f = c.MbapFramer(role)
    bounds = [0, *cuts, len(data)]
    for a, b in itertools.pairwise(bounds):
        if a < b:  # b"" would end the stream
            f.receive_data(data[a:b])
    f.receive_data(b"")
    framed = [(e.kind, e.adu, e.offset, e.error) for e in f.events()]
    good_parsed = [e for e in entries if e[3] is None]
    assert [e for e in framed if e[3] is None] == good_parsed
    assert [(e[2], e[3]) for e in framed if e[3]] == [(e[2], e[3]) for e in entries if e[3]]


def _outcome(fn: object, *args: object) -> object:
    try:
        return fn(*args)  # type: ignore[operator]
    except Exception as exc:
        return (type(exc), str(exc))


@SETTINGS
@given(
    tid=st.one_of(
        st.integers(-5, 70_000), st.booleans(), st.floats(allow_nan=False), st.text(max_size=2)
    ),
    unit=st.one_of(st.integers(-5, 300), st.none()),
    body=st.one_of(st.binary(max_size=260), st.text(max_size=3), st.integers()),
)
def test_encode_agrees_on_results_and_errors(
    both: tuple[ModuleType, ModuleType], tid: object, unit: object, body: object
) -> None:
    c, py = both
    assert _outcome(c.encode_mbap, tid, unit, body) == _outcome(py.encode_mbap, tid, unit, body)
    framed = [_outcome(m.MbapFramer("master").send, tid, unit, body) for m in (c, py)]
    assert framed[0] == framed[1]


def test_backends_export_the_same_names() -> None:
    for name in ("MbapFramer", "parse_tcp_stream", "encode_mbap"):
        for b in pyrtu.available_backends():
            assert hasattr(pyrtu.backend(b), name)
