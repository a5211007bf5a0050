"""Property tests: the C core and the pure-Python twin agree on random input."""

from __future__ import annotations

from types import ModuleType

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
