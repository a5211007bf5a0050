"""The outbox where the mutation runs (docs/MUTATION.md) found it untested: the
budget at its exact boundaries (a record needing exactly the oldest segment's room,
one byte more, a new segment's header; "refuse" taking records again), a record
found at the very start of a chunk or straddling two when resynchronising, the
largest sequence number, the reserved block's end, restarts and crash gaps, what
an Outbox leaves behind (descriptors, deleted files held open, file modes), the
costs the bridge pays at each call (batched writes, reads resumed at the hint,
oldest_time read once per ack cursor), short writes, damage found while open.
Sizes from the format (pyrtu/outbox/_format.py: a 16-byte segment header, a
28-byte record header, 40-byte cursor slots at 0 and 512); the bytes of files
built or read here are laid out with struct from that module's docstring."""

from __future__ import annotations

import contextlib
import json
import os
import stat
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import pytest

from pyrtu.outbox import _format as fmt
from pyrtu.outbox.outbox import Outbox, OutboxFull, OutboxLimits

SEGMENT = 1024
#: one record fills a segment: 16 + 28 + 980 = 1024 bytes
PAYLOAD = SEGMENT - 16 - 28


def test_a_record_needing_exactly_the_oldest_segment_drops_only_that(tmp_path: Path) -> None:
    limits = OutboxLimits(max_bytes=3 * SEGMENT, segment_bytes=SEGMENT)
    with Outbox(tmp_path / "ob", limits) as box:
        for i in range(3):
            box.append(bytes([i]) * PAYLOAD, now=float(i))
        assert box.bytes_used == 3 * SEGMENT and box.depth == 3
        box.append(b"\x03" * PAYLOAD, now=3.0)  # needs one segment's room, exactly
        assert box.dropped == 1 and box.depth == 3


# -- the format at its edges (records and cursor slots built with struct from the
# layout in pyrtu/outbox/_format.py's docstring, not by the code under test) -------

REC_PRE = struct.Struct("<4sIQd")  # magic, payload length, seq, time
SLOT = struct.Struct("<4sQQQQ")  # magic, generation, acked, reserved, dropped


def _record(seq: int, now: float, payload: bytes) -> bytes:
    pre = REC_PRE.pack(b"\xb7OBr", len(payload), seq, now)
    return pre + struct.pack("<I", zlib.crc32(pre + payload)) + payload


def test_a_record_right_after_one_bad_byte_is_found_at_a_chunk_start() -> None:
    """One stray byte, then a record: resynchronising, the scan reads a fresh chunk
    from the byte after the bad one, and the record's magic is its very first byte."""
    head = b"\x00" * 16  # where a segment's header stands (the scan starts after it)
    record = _record(7, 7.0, bytes(range(100)))
    data = head + b"\xee" + record
    items = list(fmt.scan(lambda off, n: data[off : off + n], 16, len(data), last_seq=0, chunk=64))
    assert [(i.off, i.end, i.seq) for i in items] == [(16, 17, -1), (17, len(data), 7)]
    assert items[1].payload == bytes(range(100))


def _slot(gen: int, acked: int, reserved: int, dropped: int) -> bytes:
    body = SLOT.pack(b"OBc1", gen, acked, reserved, dropped)
    return body + struct.pack("<I", zlib.crc32(body))


def test_sequence_numbers_end_at_the_largest_signed_64_bit_integer() -> None:
    """A cursor slot and a record may carry 2**63 - 1, not 2**63 (which the format's
    u64 could hold, but no outbox hands out): a slot or record beyond is damage."""
    top = 2**63 - 1
    assert fmt.decode_state(_slot(1, top, top, 0)) == fmt.CursorState(1, top, top, 0)
    assert fmt.decode_state(_slot(1, 0, top + 1, 0)) is None
    data = b"\x00" * 16 + _record(top, 1.0, b"last") + _record(top + 1, 2.0, b"past")
    items = list(fmt.scan(lambda off, n: data[off : off + n], 16, len(data), last_seq=0))
    assert [(i.seq, i.payload) for i in items] == [(top, b"last"), (-1, None)]


# -- what an open and a closed Outbox show ------------------------------------------


def test_repr_and_the_ack_range_name_the_numbers(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    box = Outbox(d, OutboxLimits(max_bytes=4 * SEGMENT, segment_bytes=SEGMENT))
    box.append(b"one", now=1.0)
    box.append(b"two", now=2.0)
    assert repr(box) == f"<Outbox {str(d)!r} depth=2 next_seq=3>"
    with pytest.raises(ValueError) as info:
        box.ack(3)
    assert str(info.value) == "seq must be in 0..2 (appended so far), got 3"
    box.close()
    assert repr(box) == f"<Outbox {str(d)!r} closed>"


# -- resources: a deleted segment is not held open -----------------------------------


def _held_deleted(directory: Path) -> list[str]:
    """The files of `directory` this process holds open though they are deleted (their
    disk space is not freed while a descriptor holds them)."""
    held = []
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/self/fd/{fd}")
            if target.startswith(str(directory)) and target.endswith(" (deleted)"):
                held.append(target)
    return held


def _file_of(fd: int, directory: Path) -> str | None:
    """The name of the file `fd` is open on if it is under `directory` (the spies
    below note only this test's files: other tests' threads may do I/O meanwhile)."""
    try:
        target = os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return None
    return os.path.basename(target) if target.startswith(str(directory)) else None


def test_an_acked_segment_read_before_frees_its_disk_space(tmp_path: Path) -> None:
    """A sealed segment read by `pending` (its descriptor kept for the next read) and
    then acked is deleted and its descriptor closed: nothing holds its blocks."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for i in range(3):
            box.append(bytes([i]) * PAYLOAD, now=float(i))  # one segment each
        box.flush()
        assert [seq for seq, _ in box.pending(1)] == [1]  # read from the sealed 1st
        box.ack(1)
        assert not (d / fmt.segment_name(1)).exists()
        assert _held_deleted(d) == []
        assert [seq for seq, _ in box.pending(1)] == [2]  # read from the sealed 2nd
        box.ack(2)
        assert _held_deleted(d) == []
        assert box.pending(5) == [(3, b"\x02" * PAYLOAD)]


# -- costs the bridge pays at every append, ack and metrics scrape -----------------


def test_appends_after_a_flush_reach_the_file_only_at_the_next_flush(tmp_path: Path) -> None:
    """Appends are buffered and written in batches (at a flush, or 256 KiB): a record
    that starts a new segment right after a flush does not make the next appends
    write, the new segment file stays empty until the flush writes it in one go."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        box.append(b"\x00" * PAYLOAD, now=0.0)  # fills the first segment
        box.flush()
        second = d / fmt.segment_name(2)
        for seq in (2, 3, 4):
            assert box.append(b"x" * 10, now=float(seq)) == seq
            assert second.stat().st_size == 0
        box.flush()
        data = second.read_bytes()
        assert len(data) == 16 + 3 * (28 + 10)
        assert struct.unpack_from("<8sQ", data) == (b"pyrtuOB\x01", 2)
        assert [REC_PRE.unpack_from(data, 16 + i * 38)[2] for i in range(3)] == [2, 3, 4]


def test_oldest_time_is_read_from_disk_once_per_ack_cursor(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """stats() (every metrics scrape) asks oldest_time: it reads the oldest unacked
    record once, then again only when the ack cursor moves; an ack that moves
    nothing (the same number again, or a lower one) keeps what was read."""
    reads: list[int] = []
    real_pread = os.pread

    def pread(fd: int, n: int, off: int) -> bytes:
        if _file_of(fd, tmp_path) is not None:
            reads.append(off)
        return real_pread(fd, n, off)

    with Outbox(tmp_path / "ob", OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for seq in (1, 2, 3):
            box.append(b"r" * 10, now=10.0 + seq)
        box.flush()  # written: the records are read back with pread
        box.ack(1)
        monkeypatch.setattr(os, "pread", pread)
        assert box.oldest_time == 12.0 and reads
        reads.clear()
        assert box.oldest_time == 12.0 and box.stats()["oldest_time"] == 12.0
        box.ack(1)
        box.ack(0)
        assert box.oldest_time == 12.0
        assert reads == []
        box.ack(2)
        assert box.oldest_time == 13.0 and reads


def test_a_segment_dropped_before_its_first_flush_leaves_the_others_synced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """drop-oldest deletes a sealed segment whose fsync is still due: its descriptor
    is closed at once, and the next flush fdatasyncs every segment that is left
    (the files are named by the descriptors the real fdatasync is given)."""
    synced: list[str] = []
    real_fdatasync = os.fdatasync

    def fdatasync(fd: int) -> None:
        name = _file_of(fd, tmp_path)
        if name is not None:
            synced.append(name)
        real_fdatasync(fd)

    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=3 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for i in range(3):
            box.append(bytes([i]) * PAYLOAD, now=float(i))  # segments 1, 2, 3; no flush
        monkeypatch.setattr(os, "fdatasync", fdatasync)
        box.append(b"\x03" * PAYLOAD, now=3.0)  # drops segment 1
        assert box.dropped == 1 and not (d / fmt.segment_name(1)).exists()
        assert _held_deleted(d) == []
        box.flush()
        segs = sorted(name for name in synced if name.endswith(".seg"))
        assert segs == [fmt.segment_name(seq) for seq in (2, 3, 4)]
        assert [seq for seq, _ in box.pending(5)] == [2, 3, 4]


# -- what the outbox leaves behind in the process and on disk -------------------------


def _open_fds(directory: Path) -> tuple[list[str], list[str]]:
    """What stdin, stdout and stderr are open on, and the files under `directory`
    this process holds open (other tests' threads may open and close files of
    their own meanwhile: those are not looked at)."""
    std = []
    for fd in (0, 1, 2):
        try:
            std.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:
            std.append("closed")
    held = []
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            if os.readlink(f"/proc/self/fd/{name}").startswith(str(directory)):
                held.append(name)
    return std, held


def test_open_and_close_leave_the_process_descriptors_as_they_were(tmp_path: Path) -> None:
    """An Outbox closes every descriptor it opened and none it did not (stdin, stdout
    stay open): never appended to, written and read, reopened, and refused at open
    (its cursor a directory)."""
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)
    before = _open_fds(tmp_path)
    assert "closed" not in before[0] and before[1] == []
    Outbox(d, limits).close()  # nothing appended: no active segment ever
    assert _open_fds(tmp_path) == before
    with Outbox(d, limits) as box:
        for i in range(3):
            box.append(bytes([i]) * PAYLOAD, now=float(i))
        box.flush()
        assert [seq for seq, _ in box.pending(2)] == [1, 2]  # sealed segments read
    assert _open_fds(tmp_path) == before
    with Outbox(d, limits) as box:  # recovered: the last segment reopened
        assert box.depth == 3
    assert _open_fds(tmp_path) == before
    bad = tmp_path / "bad"
    (bad / "cursor").mkdir(parents=True)
    with pytest.raises(OSError, match="cursor"):
        Outbox(bad, limits)
    assert _open_fds(tmp_path) == before


def test_the_outbox_files_are_created_readable_by_all_writable_by_the_owner(
    tmp_path: Path,
) -> None:
    """The cursor and the segment files are made with mode 0o644 (less the umask):
    no execute bit, no write for others."""
    old = os.umask(0o022)
    try:
        d = tmp_path / "ob"
        with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
            box.append(b"one", now=1.0)
        for name in ("cursor", fmt.segment_name(1)):
            assert stat.S_IMODE((d / name).stat().st_mode) == 0o644, name
    finally:
        os.umask(old)


# -- restarts: where the numbers and the records go on ------------------------------


def _records_in(path: Path) -> list[tuple[int, bytes]]:
    """(seq, payload) of every record of a segment file, decoded by the layout."""
    data = path.read_bytes()
    out, off = [], 16
    while off < len(data):
        _magic, n, seq, _time = REC_PRE.unpack_from(data, off)
        out.append((seq, data[off + 28 : off + 28 + n]))
        off += 28 + n
    return out


def test_a_clean_restart_goes_on_in_the_last_segment(tmp_path: Path) -> None:
    """Reopened after close(), the outbox appends to its last segment file (not a new
    one each restart): the records follow on in it, no new file appears."""
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)
    with Outbox(d, limits) as box:
        box.append(b"\x00" * PAYLOAD, now=0.0)  # segment 1, full
        box.append(b"two", now=2.0)  # segment 2
    with Outbox(d, limits) as box:
        assert box.append(b"three", now=3.0) == 3
    assert sorted(p.name for p in d.glob("*.seg")) == [fmt.segment_name(1), fmt.segment_name(2)]
    assert _records_in(d / fmt.segment_name(2)) == [(2, b"two"), (3, b"three")]


def test_after_a_crash_the_next_number_starts_a_new_segment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A crash leaves the cursor's reserved block ahead of the last record (here:
    records 1 and 2, reserved 100, built by the layout): the numbers go on at 100,
    in a new segment named by it; asked for the records after 2 (inside the gap), the
    outbox reads none of the segment before the gap, and an ack inside the gap still
    leaves 100 pending."""
    read_from: list[str] = []
    real_pread = os.pread

    def pread(fd: int, n: int, off: int) -> bytes:
        name = _file_of(fd, tmp_path)
        if name is not None:
            read_from.append(name)
        return real_pread(fd, n, off)

    d = tmp_path / "ob"
    d.mkdir()
    (d / "cursor").write_bytes(_slot(1, 0, 100, 0) + bytes(512))
    seg = struct.pack("<8sQ", b"pyrtuOB\x01", 1) + _record(1, 1.0, b"a") + _record(2, 2.0, b"b")
    (d / fmt.segment_name(1)).write_bytes(seg)
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        assert box.next_seq == 100 and box.depth == 2
        assert box.append(b"c", now=3.0) == 100
        assert box.append(b"\x04" * PAYLOAD, now=4.0) == 101  # segment 101
        box.flush()
        assert _records_in(d / fmt.segment_name(100)) == [(100, b"c")]
        assert _records_in(d / fmt.segment_name(1)) == [(1, b"a"), (2, b"b")]
        after_gap = [(100, b"c"), (101, b"\x04" * PAYLOAD)]
        monkeypatch.setattr(os, "pread", pread)
        assert box.pending(5, after=2) == after_gap  # from inside the gap
        assert fmt.segment_name(1) not in read_from
        assert fmt.segment_name(100) in read_from
        box.ack(50)  # every record up to 50 is delivered: 1 and 2
        assert box.depth == 2 and box.pending(5) == after_gap


def test_an_opened_outbox_has_its_next_numbers_reserved_on_disk(tmp_path: Path) -> None:
    """Opening reserves the next numbers in the cursor (read here by the layout), so
    the first appends write nothing to it."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        cursor = (d / "cursor").read_bytes()
        slots = [SLOT.unpack_from(cursor, off) for off in (0, 512)]
        _magic, _gen, acked, reserved, _dropped = max(s for s in slots if s[0] == b"OBc1")
        assert acked == 0 and reserved > box.next_seq == 1
        for seq in range(1, 11):
            assert box.append(b"r", now=float(seq)) == seq
        assert (d / "cursor").read_bytes() == cursor


def test_the_budget_counts_the_header_of_the_segment_a_record_starts(tmp_path: Path) -> None:
    """max_bytes 3080: two full segments (2048 bytes) and a third of 16 + 28 + 476 =
    520 leave 512 bytes; a record of 28 + 480 = 508 bytes would fit them, but it does
    not fit the third segment (1024 bytes), so it starts a fourth, which needs its
    16-byte header too: 524 > 512, the oldest segment is dropped for it."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=3080, segment_bytes=SEGMENT)) as box:
        box.append(b"\x00" * PAYLOAD, now=0.0)
        box.append(b"\x01" * PAYLOAD, now=1.0)
        box.append(b"\x02" * 476, now=2.0)
        assert box.bytes_used == 2 * SEGMENT + 520 and box.dropped == 0
        assert box.append(b"\x03" * 480, now=3.0) == 4
        assert box.dropped == 1 and not (d / fmt.segment_name(1)).exists()
        assert box.bytes_used == SEGMENT + 520 + 524 <= 3080
        box.flush()
        assert box.bytes_used == sum(p.stat().st_size for p in d.glob("*.seg"))


def test_appends_are_written_once_256_kib_are_buffered_not_later(tmp_path: Path) -> None:
    """At most 256 KiB of appended records wait in memory: a 16-byte header and 5461
    records of 28 + 20 bytes are exactly 262144 bytes, still unwritten; the next
    append writes them (and buffers itself)."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 21, segment_bytes=1 << 20)) as box:
        for seq in range(1, 5462):
            box.append(b"\x07" * 20, now=float(seq))
        first = d / fmt.segment_name(1)
        assert first.stat().st_size == 0
        box.append(b"\x07" * 20, now=5462.0)
        assert first.stat().st_size == 16 + 5461 * 48 == 1 << 18
        box.append(b"\x07" * 20, now=5463.0)  # buffered again, with 5462
        assert first.stat().st_size == 1 << 18
        assert _records_in(first)[-1] == (5461, b"\x07" * 20)


def test_the_budget_is_kept_to_the_byte_when_dropping_several_segments(
    tmp_path: Path,
) -> None:
    """max_bytes 2048 and three segments of 16 + 28 + 500 = 544 bytes (1632): a record
    of 28 + 917 bytes starts a fourth segment, 961 bytes; dropping the oldest leaves
    it one byte short (1088 + 961 = 2049), so the second goes too."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=2048, segment_bytes=SEGMENT)) as box:
        for i in range(3):
            box.append(bytes([i]) * 500, now=float(i))
        assert box.bytes_used == 3 * 544
        assert box.append(b"\x03" * 917, now=3.0) == 4
        assert box.dropped == 2 and box.bytes_used == 544 + 961
        box.flush()
        assert [seq for seq, _ in box.pending(5)] == [3, 4]


def test_a_record_damaged_on_disk_while_open_is_counted_with_its_bytes(
    tmp_path: Path,
) -> None:
    """A flushed record whose payload is then damaged on disk is skipped by pending,
    counted once in corrupt, and its 28 + 10 bytes in corrupt_bytes."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for seq in (1, 2, 3):
            box.append(bytes([seq]) * 10, now=float(seq))
        box.flush()
        seg = d / fmt.segment_name(1)
        with open(seg, "r+b") as f:  # record 2: at 16 + 38, its payload at +28
            f.seek(16 + 38 + 28 + 4)
            f.write(b"\xff")
        for _ in range(2):
            assert box.pending(5) == [(1, b"\x01" * 10), (3, b"\x03" * 10)]
        assert (box.corrupt, box.corrupt_bytes) == (1, 38)


def test_pending_goes_on_where_the_last_one_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A publisher asks pending(n, after=last) over and over: each call reads on from
    the end of the record the previous one returned (not again from the segment's
    start), also after an ack deleted an older segment, and opens a sealed segment
    once.  Asking again from an earlier number (the last one returned, or the first)
    still returns every record from it."""
    reads: list[int] = []
    opened: list[str] = []
    real_pread, real_open = os.pread, os.open

    def pread(fd: int, n: int, off: int) -> bytes:
        if _file_of(fd, tmp_path) is not None:
            reads.append(off)
        return real_pread(fd, n, off)

    def os_open(path: str | os.PathLike[str], flags: int, mode: int = 0o777) -> int:
        if str(path).startswith(str(tmp_path)):
            opened.append(os.path.basename(path))
        return real_open(path, flags, mode)

    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        box.append(b"\x00" * PAYLOAD, now=0.0)  # segment 1
        for seq in range(2, 22):  # segment 2: records of 28 + 10 bytes from offset 16
            box.append(bytes([seq]) * 10, now=float(seq))
        box.append(b"\x16" * PAYLOAD, now=22.0)  # segment 22
        box.flush()
        monkeypatch.setattr(os, "pread", pread)
        monkeypatch.setattr(os, "open", os_open)
        assert box.pending(3, after=1) == [(s, bytes([s]) * 10) for s in (2, 3, 4)]
        box.ack(1)  # segment 1 goes
        for first in (5, 8, 11):
            reads.clear()
            got = box.pending(3, after=first - 1)
            assert got == [(s, bytes([s]) * 10) for s in range(first, first + 3)]
            assert reads[0] == 16 + (first - 2) * 38  # where record `first` starts
        assert opened.count(fmt.segment_name(2)) == 1
        assert box.pending(2, after=12) == [(13, b"\x0d" * 10), (14, b"\x0e" * 10)]
        assert box.pending(2) == [(2, b"\x02" * 10), (3, b"\x03" * 10)]
        assert box.pending(1, after=0) == [(2, b"\x02" * 10)]  # 0: from the first


# -- segments: when one is full, sealed, deleted, not made ----------------------------


def test_a_record_that_fills_its_segment_to_the_last_byte_goes_in_it(tmp_path: Path) -> None:
    """16 + (28 + 476) * 2 = 1024: the second record fits the segment exactly."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        box.append(b"\x01" * 476, now=1.0)
        box.append(b"\x02" * 476, now=2.0)
        assert box.bytes_used == SEGMENT
        box.append(b"\x03", now=3.0)  # the next one starts a second segment
    assert sorted(p.name for p in d.glob("*.seg")) == [fmt.segment_name(1), fmt.segment_name(3)]
    assert [seq for seq, _ in _records_in(d / fmt.segment_name(1))] == [1, 2]


def test_a_segment_acked_while_active_goes_when_the_next_one_starts(tmp_path: Path) -> None:
    """Every record of the active segment acked: it stays while it takes appends, and
    is deleted as soon as a record starts the next segment."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        box.append(b"a", now=1.0)
        box.append(b"b", now=2.0)
        box.flush()
        box.ack(2)
        assert (d / fmt.segment_name(1)).exists() and box.depth == 0
        box.append(b"\x03" * PAYLOAD, now=3.0)  # does not fit: a new segment
        assert not (d / fmt.segment_name(1)).exists()
        assert box.bytes_used == SEGMENT and box.depth == 1


def test_dropping_a_partly_acked_segment_counts_its_unacked_records(tmp_path: Path) -> None:
    """Segment 1 holds records 1..10 (16 + 10 * 38 = 396 bytes), 4 of them acked;
    two full segments follow; the next full one drops segment 1: 6 records lost."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=3 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for seq in range(1, 11):
            box.append(bytes([seq]) * 10, now=float(seq))
        box.append(b"\x0b" * PAYLOAD, now=11.0)
        box.append(b"\x0c" * PAYLOAD, now=12.0)
        box.flush()
        box.ack(4)
        assert box.depth == 8 and box.dropped == 0
        box.append(b"\x0d" * PAYLOAD, now=13.0)
        assert box.dropped == 6 and box.depth == 3 and box.acked == 10


def test_a_segment_that_cannot_be_made_loses_nothing_and_leaks_nothing(tmp_path: Path) -> None:
    """The next segment's name is taken (by a directory): the append that needs it
    fails naming it, the records before are kept, close() releases exactly what was
    opened, and once the name is free the outbox goes on."""
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)
    before = _open_fds(tmp_path)
    box = Outbox(d, limits)
    box.append(b"\x01" * PAYLOAD, now=1.0)
    (d / fmt.segment_name(2)).mkdir()
    with pytest.raises(OSError, match=fmt.segment_name(2)):
        box.append(b"two", now=2.0)
    box.close()
    assert _open_fds(tmp_path) == before
    (d / fmt.segment_name(2)).rmdir()
    with Outbox(d, limits) as box:
        assert box.pending(5) == [(1, b"\x01" * PAYLOAD)]
        assert box.append(b"two", now=2.0) == 2


def test_short_writes_are_continued_where_they_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pwrite may write fewer bytes than asked (POSIX): here at most 50 a call, for
    real; the outbox writes the rest after them, and the file holds every record."""
    real_pwrite = os.pwrite

    def pwrite(fd: int, data: bytes, off: int) -> int:
        if _file_of(fd, tmp_path) is None:
            return real_pwrite(fd, data, off)
        return real_pwrite(fd, bytes(data[:50]), off)

    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        monkeypatch.setattr(os, "pwrite", pwrite)
        for seq in range(1, 6):
            box.append(bytes([seq]) * 40, now=float(seq))
        box.flush()
        monkeypatch.undo()
    assert _records_in(d / fmt.segment_name(1)) == [(s, bytes([s]) * 40) for s in range(1, 6)]
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        assert box.corrupt == 0 and [seq for seq, _ in box.pending(9)] == [1, 2, 3, 4, 5]


def test_the_number_at_the_end_of_the_reserved_block_is_reserved_before_use(
    tmp_path: Path,
) -> None:
    """Every number handed out is below the cursor's `reserved` (the format's promise:
    none is reused after a crash).  Opening reserves a block ahead; the append that
    reaches its end, exactly, writes a new block to the cursor (read by the layout)
    before it returns that number."""

    def reserved() -> int:
        cursor = (d / "cursor").read_bytes()
        slots = [SLOT.unpack_from(cursor, off) for off in (0, 512)]
        return int(max(s for s in slots if s[0] == b"OBc1")[3])

    d = tmp_path / "ob"
    with Outbox(d) as box:  # no flush: only the appends reserve
        end = reserved()
        for _ in range(end - 1):
            box.append(b"", now=0.0)
        assert box.next_seq == end and reserved() == end
        assert box.append(b"", now=0.0) == end
        assert reserved() > end


# -- the outbox's own API around the quarantine --------------------------------------


def test_quarantine_takes_sequence_numbers_from_1_and_refuses_once_closed(
    tmp_path: Path,
) -> None:
    """quarantine(seq, record, reason) copies a record to quarantine.jsonl (read back
    with json); seq 1 is the first there is, 0 is refused naming `seq`; a closed
    Outbox refuses, and the copies made are on disk."""
    d = tmp_path / "ob"
    box = Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT))
    box.append(b"topic+#\npayload", now=1.0)
    box.quarantine(1, b"topic+#\npayload", "a wildcard")
    with pytest.raises(ValueError, match="seq"):
        box.quarantine(0, b"x", "no such record")
    assert box.quarantined == 1
    box.ack(1)
    box.close()
    with pytest.raises(ValueError, match="closed"):
        box.quarantine(1, b"again", "closed")
    (line,) = box.quarantine_path.read_text().splitlines()
    doc = json.loads(line)
    assert (doc["seq"], doc["reason"], doc["record"]) == (1, "a wildcard", "topic+#\npayload")


def _reading(data: bytes) -> Callable[[int, int], bytes]:
    return lambda off, n: data[off : off + n]


def test_a_record_whose_magic_straddles_two_chunks_is_found() -> None:
    """Resynchronising, the scan looks for the next record's magic chunk by chunk
    (64 bytes, from the byte after the bad one at 16): a magic split 3 + 1, 2 + 2
    or 1 + 3 bytes across the end of the first chunk (at 81), or just after it, is
    found all the same."""
    record = _record(7, 7.0, bytes(range(30)))
    for at in (78, 79, 80, 81):
        data = b"\x00" * 16 + b"\xee" * (at - 16) + record
        items = list(fmt.scan(_reading(data), 16, len(data), last_seq=0, chunk=64))
        assert [(i.off, i.end, i.seq) for i in items] == [(16, at, -1), (at, len(data), 7)], at


def test_an_outbox_opened_with_stdin_closed_closes_descriptor_0_too(tmp_path: Path) -> None:
    """A daemon may run with stdin closed: the outbox's first file then gets
    descriptor 0, which close() must release like any other."""
    saved = os.dup(0)
    os.close(0)
    try:
        box = Outbox(tmp_path / "ob", OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT))
        assert os.readlink("/proc/self/fd/0") == str(tmp_path / "ob")  # its directory
        box.append(b"x", now=1.0)
        box.close()
        with pytest.raises(OSError):  # (listing /proc/self/fd would take 0 itself)
            os.fstat(0)
    finally:
        os.dup2(saved, 0)
        os.close(saved)


def test_a_scan_reads_each_stretch_once_and_no_further_than_its_end() -> None:
    """Three records of 28 + 36 bytes after the header (16..208), chunks of 150
    bytes: one read for the first two records and the third's header start, one for
    the rest, and that one asks only for the 64 bytes up to the end."""
    data = b"\x00" * 16 + b"".join(_record(s, float(s), bytes([s]) * 36) for s in (1, 2, 3))
    reads: list[tuple[int, int]] = []

    def read(off: int, n: int) -> bytes:
        reads.append((off, n))
        return data[off : off + n]

    items = list(fmt.scan(read, 16, len(data), last_seq=0, chunk=150))
    assert [(i.off, i.end, i.seq) for i in items] == [(16, 80, 1), (80, 144, 2), (144, 208, 3)]
    assert reads == [(16, 150), (144, 64)]


def test_a_segment_cut_short_while_open_counts_the_bytes_left_of_its_record(
    tmp_path: Path,
) -> None:
    """Records 1..3 (28 + 10 bytes each, at 16, 54, 92) in a sealed segment whose
    file is then cut 10 bytes into record 3: pending returns 1, 2 and the record of
    the next segment, and counts the 10 bytes left of record 3 as one bad region."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        for seq in (1, 2, 3):
            box.append(bytes([seq]) * 10, now=float(seq))
        box.append(b"\x04" * PAYLOAD, now=4.0)  # does not fit: segment 4
        box.flush()
        os.truncate(d / fmt.segment_name(1), 92 + 10)
        assert [seq for seq, _ in box.pending(9)] == [1, 2, 4]
        assert (box.corrupt, box.corrupt_bytes) == (1, 10)


def test_a_limit_far_beyond_the_backlog_returns_all_of_it(tmp_path: Path) -> None:
    """pending(2**21) (more than any backlog here) over a 64 KiB segment: every
    record, in order."""
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 18, segment_bytes=1 << 16)) as box:
        for seq in range(1, 501):
            box.append(seq.to_bytes(2, "big") * 50, now=float(seq))
        box.flush()
        got = box.pending(1 << 21)
        assert [seq for seq, _ in got] == list(range(1, 501))
        assert all(rec == seq.to_bytes(2, "big") * 50 for seq, rec in got)


@pytest.mark.parametrize("at", [0, 512])
def test_a_cursor_whose_newest_slot_alone_is_of_a_newer_format_is_refused(
    tmp_path: Path, at: int
) -> None:
    """A newer pyrtu that saved the cursor once leaves one slot of its version (the
    other still ours): refused as that version, whichever slot it wrote."""
    d = tmp_path / "ob"
    Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)).close()
    cursor = bytearray((d / "cursor").read_bytes())
    assert len(cursor) == 512 + 40  # slots of 36 bytes and a CRC-32
    _magic, _gen, acked, reserved, dropped = SLOT.unpack_from(cursor, at)
    body = SLOT.pack(b"OBc2", 99, acked, reserved, dropped)
    cursor[at : at + 40] = body + struct.pack("<I", zlib.crc32(body))
    (d / "cursor").write_bytes(bytes(cursor))
    with pytest.raises(OSError, match="cursor is in outbox format version 2"):
        Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT))


def test_refuse_takes_records_again_up_to_the_budget_once_a_segment_is_freed(
    tmp_path: Path,
) -> None:
    """Policy "refuse": full at 3008 bytes (three segments of 16 + 7 * 128 and a
    fourth of 16 + 2 * 128), a record of 28 + 36 bytes that would fit the 64 left is
    refused; delivery frees the first segment, and the outbox is an ordinary one
    again: back at 3008 bytes, that record fits, and is taken."""
    limits = OutboxLimits(max_bytes=3 * SEGMENT, segment_bytes=SEGMENT, policy="refuse")
    with Outbox(tmp_path / "ob", limits) as box:
        accepted = []
        with pytest.raises(OutboxFull):
            for _ in range(100):
                accepted.append(box.append(b"r" * 100, now=0.0))
        assert len(accepted) == 23 and box.bytes_used == 3008
        with pytest.raises(OutboxFull):
            box.append(b"s" * 36, now=0.0)
        box.flush()
        box.ack(7)  # the first segment delivered: it goes
        assert box.bytes_used == 3008 - 912
        for _ in range(7):
            box.append(b"r" * 100, now=0.0)
        assert box.bytes_used == 3008
        assert box.append(b"s" * 36, now=0.0) == 31
        assert box.bytes_used == 3 * SEGMENT


def test_flush_is_due_at_exactly_fsync_records_appends(tmp_path: Path) -> None:
    """fsync_records=3, fsync_interval an hour: two appends make no flush due, the
    third does; after the flush, again only the third."""
    limits = OutboxLimits(
        max_bytes=8 * SEGMENT, segment_bytes=SEGMENT, fsync_records=3, fsync_interval=3600.0
    )
    with Outbox(tmp_path / "ob", limits) as box:
        for _ in range(2):
            box.append(b"r", now=0.0)
            assert not box.flush_due(1.0)
        box.append(b"r", now=0.0)
        assert box.flush_due(1.0)
        box.flush()
        for _ in range(2):
            box.append(b"r", now=2.0)
            assert not box.flush_due(3.0)
        box.append(b"r", now=2.0)
        assert box.flush_due(3.0)


def test_a_record_replayed_at_the_start_of_a_segment_is_never_delivered(
    tmp_path: Path,
) -> None:
    """Segment 3 (built by the layout) begins with a checksummed copy of record 2 of
    segment 1, then record 3: numbers only go up, so the copy is damage, counted
    once, and record 2 is delivered once."""
    d = tmp_path / "ob"
    d.mkdir()
    head = struct.Struct("<8sQ")
    one = head.pack(b"pyrtuOB\x01", 1) + _record(1, 1.0, b"a") + _record(2, 2.0, b"b")
    three = head.pack(b"pyrtuOB\x01", 3) + _record(2, 2.0, b"b") + _record(3, 3.0, b"c")
    (d / fmt.segment_name(1)).write_bytes(one)
    (d / fmt.segment_name(3)).write_bytes(three)
    with Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)) as box:
        assert box.pending(9) == [(1, b"a"), (2, b"b"), (3, b"c")]
        assert box.corrupt == 1 and box.depth == 3


@pytest.mark.parametrize("damaged", [1, 3])
def test_depth_and_oldest_time_skip_the_numbers_of_records_damaged_before_a_restart(
    tmp_path: Path, damaged: int
) -> None:
    """Records 1..5 in one segment (10-byte payloads: 38 bytes each after the 16-byte
    header), one of them damaged on disk while the outbox is closed: the restart's
    scan drops it, so 4 remain.  Acked up to 4, only record 5 is pending: depth 1 and
    the oldest time 5's, as pending() says (a damaged number was counted as an acked
    record, depth 0 and no oldest time, so the bridge's drain stopped with record 5
    still waiting)."""
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)
    with Outbox(d, limits) as box:
        for seq in range(1, 6):
            box.append(bytes([seq]) * 10, now=float(seq))
    with open(d / fmt.segment_name(1), "r+b") as f:
        f.seek(16 + (damaged - 1) * 38 + 28 + 4)  # a byte of its payload
        f.write(b"\xff")
    with Outbox(d, limits) as box:
        assert box.depth == 4
        assert box.oldest_time == (2.0 if damaged == 1 else 1.0)
        box.ack(4)
        assert box.pending(10) == [(5, b"\x05" * 10)]
        assert box.depth == 1
        assert box.oldest_time == 5.0
        box.ack(5)
        assert box.depth == 0 and box.oldest_time is None


def test_a_torn_first_slot_does_not_hide_a_newer_format_in_the_second(tmp_path: Path) -> None:
    """The first cursor slot torn (its CRC-32 no longer matches), the second written by
    a newer pyrtu (format version 2): the outbox is refused as that version, not read
    as an empty or torn cursor of ours."""
    d = tmp_path / "ob"
    Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT)).close()
    cursor = bytearray((d / "cursor").read_bytes())
    _magic, _gen, acked, reserved, dropped = SLOT.unpack_from(cursor, 512)
    body = SLOT.pack(b"OBc2", 99, acked, reserved, dropped)
    cursor[512 : 512 + 40] = body + struct.pack("<I", zlib.crc32(body))
    cursor[36] ^= 0xFF  # slot 0's CRC-32: torn
    (d / "cursor").write_bytes(bytes(cursor))
    with pytest.raises(OSError, match="cursor is in outbox format version 2"):
        Outbox(d, OutboxLimits(max_bytes=8 * SEGMENT, segment_bytes=SEGMENT))
