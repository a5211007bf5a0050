"""The outbox's file format under damage: torn tails, flipped bytes, garbage, and
hypothesis-generated segment and cursor files (pyrtu.outbox._format)."""

from __future__ import annotations

import itertools
import os
import random
import shutil
import struct
import tempfile
import zlib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from outbox_helpers import everything, fill, payload, segments

from pyrtu.outbox import _format as fmt
from pyrtu.outbox.outbox import Outbox, OutboxError, OutboxLimits

# -- torn and corrupt records -----------------------------------------------


def _one_segment(tmp_path: Path, n: int = 100) -> tuple[Path, Path]:
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, n)
    (seg,) = segments(d)
    return d, seg


def _offset_of(seg: Path, seq: int) -> int:
    data = seg.read_bytes()
    off = fmt.SEG_HEAD.size
    while off < len(data):
        _m, n, s, _t, _c = fmt.REC_HEAD.unpack_from(data, off)
        if s == seq:
            return off
        off += fmt.REC_HEAD.size + n
    raise AssertionError(seq)


def _flip(path: Path, off: int) -> None:
    with open(path, "r+b") as f:
        f.seek(off)
        b = f.read(1)
        f.seek(off)
        f.write(bytes([b[0] ^ 0x40]))


def test_torn_tail_is_truncated_counted_and_its_number_not_reused(tmp_path: Path) -> None:
    d, seg = _one_segment(tmp_path)
    size = seg.stat().st_size
    os.truncate(seg, size - 5)  # the last record is cut short
    with Outbox(d) as ob:
        assert ob.corrupt == 1 and ob.corrupt_bytes == size - 5 - _offset_of(seg, 99) - (
            fmt.REC_HEAD.size + len(payload(99))
        )
        got = everything(ob)
        assert [s for s, _ in got] == list(range(1, 100))
        assert all(rec == payload(s) for s, rec in got)
        assert seg.stat().st_size == _offset_of(seg, 99) + fmt.REC_HEAD.size + len(payload(99))
        assert ob.append(b"new", 0.0) == 101  # 100 was handed out once: never again


@pytest.mark.parametrize("where", ["payload", "length", "seq", "crc", "magic"])
def test_flipped_byte_skips_only_that_record(tmp_path: Path, where: str) -> None:
    d, seg = _one_segment(tmp_path)
    delta = {"magic": 1, "length": 5, "seq": 9, "crc": 25, "payload": 28}[where]
    _flip(seg, _offset_of(seg, 50) + delta)
    with Outbox(d) as ob:
        got = everything(ob)
        assert [s for s, _ in got] == [s for s in range(1, 101) if s != 50]
        assert all(rec == payload(s) for s, rec in got)
        assert ob.corrupt == 1 and ob.corrupt_bytes > 0 and ob.depth == 99
        assert ob.next_seq == 101


def test_corruption_while_open_is_skipped_and_counted_once(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, 100)
        ob.flush()
        (seg,) = segments(d)
        _flip(seg, _offset_of(seg, 7) + 30)
        for _ in range(2):
            got = everything(ob)
            assert [s for s, _ in got] == [s for s in range(1, 101) if s != 7]
        assert ob.corrupt == 1


@pytest.mark.parametrize("bad", [[100], [98, 99, 100], list(range(1, 101))])
def test_records_damaged_while_open_after_the_last_readable_one_are_passed_by_the_acks(
    tmp_path: Path, bad: list[int]
) -> None:
    """Records damaged on disk while the outbox is open (a payload byte flipped), with
    no readable record after them: they can never be delivered, so the ack of the
    last readable one passes them (all of them damaged: at once); the depth falls to
    0, no oldest time, nothing pending (the depth stayed at the number damaged, and a
    drain waited for records it could never send).  A record appended after them is
    delivered as usual."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, 100)
        ob.flush()
        (seg,) = segments(d)
        for seq in bad:
            _flip(seg, _offset_of(seg, seq) + fmt.REC_HEAD.size)
        good = [s for s in range(1, 101) if s not in bad]
        assert [s for s, _ in everything(ob)] == good
        assert ob.corrupt >= 1
        if good:
            assert ob.acked == 0 and ob.depth == 100
            ob.ack(good[-1])
        assert ob.acked == 100 and ob.depth == 0 and ob.oldest_time is None
        assert ob.pending(10) == []
        assert ob.append(b"next", 1.0) == 101
        ob.flush()
        assert ob.pending(10) == [(101, b"next")] and ob.depth == 1


def test_an_unreadable_tail_is_passed_only_by_the_ack_reaching_it(tmp_path: Path) -> None:
    """Record 100 damaged while open, 1..99 handed out in two batches: an ack of 50
    leaves 51..99 and nothing of 100 acked (depth 50); the ack of 99 passes 100."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, 100)
        ob.flush()
        (seg,) = segments(d)
        _flip(seg, _offset_of(seg, 100) + fmt.REC_HEAD.size)
        assert [s for s, _ in ob.pending(60)] == list(range(1, 61))
        assert [s for s, _ in ob.pending(60, after=60)] == list(range(61, 100))
        ob.ack(50)
        assert ob.acked == 50 and ob.depth == 50
        ob.ack(98)
        assert ob.acked == 98 and ob.depth == 2
        ob.ack(99)
        assert ob.acked == 100 and ob.depth == 0


def test_unreadable_records_after_one_in_flight_wait_for_its_ack(tmp_path: Path) -> None:
    """Records 6..10 damaged while open; 1..5 handed out, 4 acked, 5 in flight (a
    publish cursor at 5): nothing after the cursor reads, yet the acks stay at 4
    (record 5 is not delivered yet) until 5 is acked, which passes 6..10 too."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, 10)
        ob.flush()
        (seg,) = segments(d)
        for seq in range(6, 11):
            _flip(seg, _offset_of(seg, seq) + fmt.REC_HEAD.size)
        assert [s for s, _ in ob.pending(5)] == [1, 2, 3, 4, 5]
        ob.ack(4)
        assert ob.pending(10, after=5) == []
        assert ob.acked == 4 and ob.depth == 6
        ob.ack(5)
        assert ob.acked == 10 and ob.depth == 0


def _rec(seq: int, now: float, payload: bytes) -> bytes:
    """A record as the format's header documents it: magic, length, sequence
    number, time (REC_PRE), then the CRC-32 of all that and the payload."""
    pre = struct.pack("<4sIqd", b"\xb7OBr", len(payload), seq, now)
    return pre + struct.pack("<I", zlib.crc32(pre + payload)) + payload


@pytest.mark.parametrize("chunk", [28, 64, 100, 4096])
@pytest.mark.parametrize("told", [0, 1, 38, 5000])
def test_a_scan_told_a_larger_end_than_the_file_has_finds_every_record_it_has(
    chunk: int, told: int
) -> None:
    """Record 1, one bad byte, records 2 and 3, in a file ``told`` bytes shorter than
    the scan is told (a file cut short while open): after the bad byte the scan
    still finds 2 and 3 in the bytes that exist, whatever the chunk, and reports no
    bad region where the file simply ends (it gave the valid records after a bad
    region up as a torn tail when its read came up short)."""
    head = b"\0" * 16
    one, two, three = _rec(1, 1.0, b"a" * 10), _rec(2, 2.0, b"b" * 10), _rec(3, 3.0, b"c" * 10)
    data = head + one + b"\xee" + two + three
    items = list(
        fmt.scan(lambda off, n: data[off : off + n], 16, len(data) + told, last_seq=0, chunk=chunk)
    )
    a = 16 + len(one)
    assert [(i.off, i.end, i.seq) for i in items] == [
        (16, a, 1),
        (a, a + 1, -1),
        (a + 1, a + 1 + len(two), 2),
        (a + 1 + len(two), len(data), 3),
    ]
    assert [i.payload for i in items] == [b"a" * 10, None, b"b" * 10, b"c" * 10]


def test_a_sealed_segment_cut_short_while_open_keeps_the_records_it_still_has(
    tmp_path: Path,
) -> None:
    """A sealed segment with a record damaged, then cut short on disk while the
    outbox is open (its last record cut in half): pending still delivers every
    record the file has after the damaged one; only the cut record is lost."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 20, segment_bytes=4096)) as ob:
        fill(ob, 300)  # several segments of 4 KiB
        ob.flush()
        first = segments(d)[0]
        data = first.read_bytes()
        seqs = [i.seq for i in fmt.scan(lambda o, n: data[o : o + n], 16, len(data), last_seq=0)]
        assert len(seqs) >= 10 and seqs[0] == 1
        _flip(first, _offset_of(first, 3) + fmt.REC_HEAD.size)
        cut = _offset_of(first, seqs[-1]) + 10
        os.truncate(first, cut)
        got = [s for s, _ in everything(ob)]
        assert got == [s for s in range(1, 301) if s not in (3, seqs[-1])]


def test_garbage_tail_and_bad_cursor_file(tmp_path: Path) -> None:
    d, seg = _one_segment(tmp_path)
    with Outbox(d) as ob:
        ob.ack(30)
    with open(seg, "ab") as f:
        f.write(random.Random(3).randbytes(3000) + fmt.REC_MAGIC + b"\x00" * 40)
    (d / "cursor").write_bytes(b"\xff" * 600)  # the cursor is unreadable: all pending again
    with Outbox(d) as ob:
        assert ob.corrupt == 2 and ob.acked == 0
        assert [s for s, _ in everything(ob)] == list(range(1, 101))
        assert ob.next_seq == 101


def test_foreign_file_in_the_directory_is_an_error_naming_it(tmp_path: Path) -> None:
    d, _seg = _one_segment(tmp_path)
    (d / f"{'9' * 20}.seg").write_bytes(b"not a segment at all, but long enough")
    with pytest.raises(OutboxError, match=r"99999999999999999999\.seg is not an outbox segment"):
        Outbox(d)
    Path(d / f"{'9' * 20}.seg").unlink()
    Outbox(d).close()  # the failed open released the lock


def test_reopening_with_smaller_segments_keeps_every_record(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        big = [ob.append(bytes([i]) * 3000, 0.0) for i in range(10)]
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1024)) as ob:
        assert everything(ob) == [(s, bytes([s - 1]) * 3000) for s in big]
        assert ob.corrupt == 0


# -- fuzzing the format ------------------------------------------------------

CHUNK = st.one_of(
    st.tuples(st.just("intact"), st.binary(max_size=300)),
    st.tuples(
        st.just("flip"), st.binary(max_size=300), st.integers(0, 10_000), st.integers(1, 255)
    ),
    st.tuples(st.just("cut"), st.binary(max_size=300), st.integers(1, 10_000)),
    st.tuples(st.just("junk"), st.binary(max_size=200)),
    st.tuples(st.just("skip"), st.integers(1, 5)),  # a gap in the numbers (a crash's)
    st.tuples(st.just("replay"), st.binary(max_size=50)),  # valid, but an old number
)


def _build(chunks: list[Any]) -> tuple[bytes, list[tuple[int, bytes]], bool]:
    """A segment (first sequence 1) of damaged and intact records, the intact ones,
    and whether anything in it is damaged."""
    data = bytearray(fmt.segment_header(1))
    damaged = False
    intact: list[tuple[int, bytes]] = []
    seq = 1
    for kind, *args in chunks:
        if kind == "junk":
            data += args[0]
            damaged = damaged or bool(args[0])
            continue
        if kind == "skip":
            seq += args[0]
            continue
        if kind == "replay":  # checksum right, number not above the last valid one
            data += fmt.encode_record(intact[-1][0] if intact else 0, 0.0, args[0])
            damaged = True
            continue
        body = args[0]
        assert isinstance(body, bytes)
        rec = bytearray(fmt.encode_record(seq, float(seq), body))
        if kind == "flip":
            pos, bits = args[1], args[2]
            assert isinstance(pos, int) and isinstance(bits, int)
            rec[pos % len(rec)] ^= bits
            damaged = True
        elif kind == "cut":
            cut = args[1]
            assert isinstance(cut, int)
            at = cut % len(rec)
            rec[at:] = bytes([rec[at] ^ 0xFF])  # cut short: what follows cannot complete it
            damaged = True
        else:
            intact.append((seq, body))
        data += rec
        seq += 1
    return bytes(data), intact, damaged


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(chunks=st.lists(CHUNK, max_size=30), chunk=st.sampled_from([29, 64, 1000, 1 << 18]))
def test_scan_finds_exactly_the_intact_records(
    chunks: list[tuple[object, ...]], chunk: int
) -> None:
    data, intact, _damaged = _build(chunks)
    items = list(
        fmt.scan(
            lambda off, n: data[off : off + n],
            fmt.SEG_HEAD.size,
            len(data),
            last_seq=0,
            chunk=chunk,
        )
    )
    # the items tile the segment: every byte is in one record or one bad region
    starts = [fmt.SEG_HEAD.size] + [i.end for i in items[:-1]]
    assert [i.off for i in items] == (starts if items else [])
    assert (items[-1].end if items else fmt.SEG_HEAD.size) == len(data)
    assert all(i.end > i.off for i in items)
    assert [(i.seq, i.payload) for i in items if i.seq >= 0] == intact
    assert all(i.time == float(i.seq) for i in items if i.seq >= 0)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(chunks=st.lists(CHUNK, max_size=20), state=st.binary(max_size=600))
def test_recovery_of_fuzzed_files(chunks: list[Any], state: bytes) -> None:
    data, intact, damaged = _build(chunks)
    d = Path(tempfile.mkdtemp(prefix="obx-fuzz-"))
    try:
        (d / fmt.segment_name(1)).write_bytes(data)
        (d / "cursor").write_bytes(state)  # random: almost never a valid slot
        with Outbox(d) as ob:
            got = everything(ob)
            assert got == [r for r in intact if r[0] > ob.acked]
            assert ob.depth == len(got)
            assert ob.next_seq > max([s for s, _ in intact] + [ob.acked])
            bad_cursor = bool(state.strip(b"\0")) and fmt.decode_state(state) is None
            assert (ob.corrupt > 0) == (damaged or bad_cursor)
            corrupt = ob.corrupt
            seq = ob.append(b"after", 1.0)
            ob.flush()
            assert ob.pending(1, after=seq - 1) == [(seq, b"after")]
        with Outbox(d) as ob:  # what recovery repaired stays repaired
            assert everything(ob)[-1] == (seq, b"after")
            assert ob.corrupt <= corrupt  # the torn tail, if any, is gone
    finally:
        shutil.rmtree(d)


@settings(max_examples=500, deadline=None)
@given(data=st.binary(max_size=fmt.STATE_SIZE + 10), flips=st.lists(st.integers(0, 600)))
def test_cursor_slots_survive_any_damage_to_the_other(data: bytes, flips: list[int]) -> None:
    assert fmt.decode_state(data) is None or isinstance(fmt.decode_state(data), fmt.CursorState)
    a = fmt.CursorState(7, 100, 200, 3)
    b = fmt.CursorState(8, 150, 200, 4)
    buf = bytearray(fmt.STATE_SIZE)
    for st_ in (a, b):
        off, raw = fmt.encode_state(st_)
        buf[off : off + len(raw)] = raw
    assert fmt.decode_state(bytes(buf)) == b
    # damage confined to one slot leaves the other one readable
    slot_b = fmt.encode_state(b)[0]
    for f in flips:
        buf[slot_b + f % (fmt.STATE.size + fmt.CRC.size)] ^= 0xA5
    assert fmt.decode_state(bytes(buf)) in (a, b)
    if flips:
        assert fmt.decode_state(bytes(buf)) == a or len(flips) % 2 == 0


def test_a_cursor_slot_with_huge_numbers_is_not_trusted(tmp_path: Path) -> None:
    d, _seg = _one_segment(tmp_path)
    good = fmt.CursorState(gen=4, acked=10, reserved=101, dropped=0)
    forged = fmt.CursorState(gen=5, acked=10, reserved=2**64 - 1, dropped=0)  # checksum right
    buf = bytearray(fmt.STATE_SIZE)
    for state in (good, forged):
        off, raw = fmt.encode_state(state)
        buf[off : off + len(raw)] = raw
    assert fmt.decode_state(bytes(buf)) == good
    (d / "cursor").write_bytes(bytes(buf))
    with Outbox(d) as ob:
        assert ob.acked == 10 and ob.next_seq == 101
        assert ob.append(b"x", 0.0) == 101


def _slot(gen: int, acked: int) -> bytes:
    """A cursor slot as the format's docstring gives it: magic "OBc1", gen, acked,
    reserved, dropped (little-endian 64-bit), then the CRC-32 of those 36 bytes."""
    body = struct.pack("<4sQQQQ", b"OBc1", gen, acked, 0, 0)
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.mark.parametrize("torn", [1, 4, 39])
def test_a_cursor_whose_second_slot_is_torn_reads_its_first(torn: int) -> None:
    """Slot 0 whole, slot 1 (at 512) cut ``torn`` bytes short of its 40: the version
    and the state are slot 0's, the torn slot ignored (not read past the data)."""
    data = _slot(4, 17).ljust(512, b"\0") + _slot(5, 18)[:-torn]
    assert fmt.cursor_version(data) == 1
    assert fmt.decode_state(data) == fmt.CursorState(4, 17, 0, 0)


def test_a_scan_from_the_middle_of_a_segment_never_goes_back() -> None:
    """A scan started after records 1 and 2 (as pending starts at an index offset),
    with only 2 stray bytes after them: one bad region of those 2 bytes, nothing
    before where it started (records 1 and 2 lie behind it)."""
    data = b"\0" * 16 + _rec(1, 1.0, b"a") + _rec(2, 2.0, b"b") + b"\xee\xee"
    start = len(data) - 2
    items = itertools.islice(
        fmt.scan(lambda off, n: data[off : off + n], start, len(data), last_seq=0), 5
    )
    assert [(i.off, i.end, i.seq) for i in items] == [(start, len(data), -1)]


def test_a_segment_header_is_its_first_16_bytes() -> None:
    """ "pyrtuOB" + version 1, then the first sequence number (little-endian 64-bit):
    parsed from exactly 16 bytes or more (a whole file's start); fewer: no header."""
    head = struct.pack("<8sQ", b"pyrtuOB\x01", 42)
    assert fmt.parse_segment_header(head) == 42
    assert fmt.parse_segment_header(head + b"\xb7OBr") == 42
    assert fmt.parse_segment_header(head[:15]) is None
    assert fmt.parse_segment_header(b"") is None


@pytest.mark.parametrize("damage", ["crc", "magic", "number"])
def test_a_cursor_whose_first_slot_is_bad_reads_its_second(damage: str) -> None:
    """Slot 0 with a wrong checksum, or a whole slot (its checksum right) of another
    magic ("OBc2") or with a number above 2**63 - 1 (none this format writes): slot
    1 (at 512) is the state, slot 0 passed over."""
    if damage == "crc":
        first = _slot(4, 17)[:-1] + b"\x00"
    else:
        magic, acked = (b"OBc2", 17) if damage == "magic" else (b"OBc1", 2**63)
        body = struct.pack("<4sQQQQ", magic, 4, acked, 0, 0)
        first = body + struct.pack("<I", zlib.crc32(body))
    data = first.ljust(512, b"\0") + _slot(3, 16)
    assert fmt.decode_state(data) == fmt.CursorState(3, 16, 0, 0)


@pytest.mark.parametrize(("head", "version"), [
    (b"pyrtuOB\x02" + b"\x00" * 8, 2),  # a whole header of version 2
    (b"pyrtuOB\x02" + b"\x00" * 12, 2),  # more bytes than the header: its version
    (b"pyrtuOB\x02" + b"\x00" * 7, 1),  # one byte short: no header (the current one)
    (b"pyrtuOB\x02", 1),
])  # fmt: skip
def test_a_segment_version_is_read_from_a_whole_header_only(head: bytes, version: int) -> None:
    assert fmt.segment_version(head) == version


def test_a_scans_numbers_are_keywords_only() -> None:
    data = b"\0" * 16
    with pytest.raises(TypeError):
        fmt.scan(lambda off, n: data[off : off + n], 16, 16, 0)  # type: ignore[misc]
