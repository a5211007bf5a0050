"""Capture files read in streaming: the merge, the frames, damaged files, memory."""

from __future__ import annotations

import functools
import os
import random
import subprocess
import sys
import textwrap
from pathlib import Path
from types import ModuleType

import pytest
from c_core import needs_c

from pyrtu.core import _backend
from pyrtu.core.frames import ErrorReason
from pyrtu.vbus.capture import (
    RECORD,
    CaptureError,
    CaptureHeader,
    CaptureReader,
    capture_frames,
    load_capture,
    read_capture,
    stream_frames,
)

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

import capsynth  # noqa: E402

CHAR = capsynth.CHAR_NS


def write(path: Path, records: list[tuple[int, int, bytes]], drops: int = 3) -> None:
    """Records (t_us, drop field, data) after a valid header."""
    with open(path, "wb") as f:
        f.write(capsynth.header(drops).line())
        for t_us, drop, data in records:
            f.write(RECORD.pack(t_us, drop, len(data)) + data)


def naive_merge(path: Path) -> tuple[bytes, list[int], list[int]]:
    """The reference: every byte sorted by (reception time, file position)."""
    raw = path.read_bytes()
    at = raw.index(b"\n") + 1
    entries = []
    seq = 0
    while at + RECORD.size <= len(raw):
        t_us, drop, n = RECORD.unpack_from(raw, at)
        data = raw[at + RECORD.size : at + RECORD.size + n]
        at += RECORD.size + n
        for k, b in enumerate(data):
            entries.append((t_us * 1000 + (k + 1) * CHAR, seq, b, drop & 0x7FFF))
            seq += 1
    entries.sort()
    return bytes(e[2] for e in entries), [e[0] for e in entries], [e[3] for e in entries]


def test_merge_is_a_sort_by_reception_time(tmp_path: Path) -> None:
    # Out-of-order records (written when runs end), overlapping runs of two drops
    # (a collision), equal times (file order decides), and long runs.
    rng = random.Random(7)
    records = []
    for i in range(400):
        t_us = i * 3000 + rng.randrange(-2500, 2500) + 5000
        drop = rng.randrange(3) | (0x8000 if rng.random() < 0.1 else 0)
        records.append((t_us, drop, bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))))
    records.append((10_000, 1, b"\x55" * 300))  # a long run overlapping many others
    records.append((10_000, 2, b"\xaa" * 5))  # same start: after drop 1's bytes of equal time
    path = tmp_path / "mixed.cap"
    write(path, records)
    data, times_ns, drops = naive_merge(path)
    cap = load_capture(str(path))
    assert cap.data == data
    assert list(cap.drops) == drops
    assert [round(t * 1e9) for t in cap.times] == times_ns
    assert cap.truncated is None
    assert len(cap.records) == len(records)
    # chunks: one per run of back-to-back bytes, offsets ascending, timed at the run's end
    chunks = cap.chunks
    assert len(chunks) < len(data) and chunks[0][0] == 0
    ends = [o for o, _ in chunks[1:]] + [len(data)]
    for (offset, t), end in zip(chunks, ends, strict=True):
        assert end > offset
        assert t == pytest.approx(cap.times[end - 1])
    assert read_capture(str(path)) == (cap.data, chunks)


def test_capture_frames_streams_what_parse_stream_finds(
    tmp_path: Path, backend: ModuleType
) -> None:
    path = tmp_path / "poll.cap"
    with open(path, "wb") as f:
        frames = capsynth.write_valid(f, 200_000, registers=10)
    cap = load_capture(str(path))
    bulk = cap.parse(backend=backend.BACKEND)
    streamed = list(capture_frames(str(path), backend=backend.BACKEND))
    assert len(streamed) == len(bulk) == frames
    assert [f.adu for f in streamed] == [f.adu for f in bulk]
    assert [f.kind for f in streamed] == [f.kind for f in bulk]
    assert all(f.error is None for f in streamed)
    # frame times: the wire times of the capture (within a microsecond of rounding)
    for s, b in zip(streamed[:50], bulk[:50], strict=True):
        assert s.start == pytest.approx(b.start, abs=2e-6)
        assert s.end == pytest.approx(b.end, abs=2e-6)


def test_a_garbled_frame_is_one_discard_run(tmp_path: Path, backend: ModuleType) -> None:
    # The live framer resolves a garbled frame in steps (1 byte "crc", then 7
    # "truncated"); streamed captures report the run whole, as parse_stream does.
    (_, req), (_, resp) = capsynth.transactions(2)[:2]
    bad = bytes([req[0], req[1], req[2] ^ 0x80]) + req[3:]
    t = 0
    records = []
    for drop, data in ((0, req), (1, resp), (0, bad), (0, req), (1, resp)):
        records.append((t, drop, data))
        t += (len(data) * CHAR + 10 * CHAR) // 1000
    path = tmp_path / "garbled.cap"
    write(path, records)
    streamed = list(capture_frames(str(path), backend=backend.BACKEND))
    bulk = load_capture(str(path)).parse(backend=backend.BACKEND)
    assert [(e.offset, e.adu) for e in streamed] == [(e.offset, e.adu) for e in bulk]
    assert [e.error is None for e in streamed] == [True, True, False, True, True]
    assert streamed[2].adu == bad and bulk[2].error is ErrorReason.CRC
    # the live framer names what it saw when the silence came: a frame still too
    # short for the response the third byte announces (0x80 bytes)
    assert streamed[2].error in (ErrorReason.CRC, ErrorReason.TRUNCATED)


def test_stream_frames_reads_a_raw_file_in_blocks(tmp_path: Path, backend: ModuleType) -> None:
    # A byte dump without times: the streamed frames are parse_stream's, whatever
    # the block size (frames straddle the block boundaries).
    parts = []
    for i in range(300):
        parts.append(backend.add_crc(bytes([1, 3, 0, i % 256, 0, 2])))
        parts.append(backend.add_crc(bytes([1, 3, 4, 1, 2, 3, i % 256])))
        if i % 50 == 0:
            parts.append(b"\x00\xff\x13")  # noise
    path = tmp_path / "dump.bin"
    path.write_bytes(b"".join(parts))
    bulk = backend.parse_stream(path.read_bytes(), "monitor")
    for size in (7, 1000, 1 << 16):
        with open(path, "rb") as dump:
            blocks = ((b, 0.0) for b in iter(functools.partial(dump.read, size), b""))
            streamed = list(stream_frames(blocks, backend=backend.BACKEND))
        assert [(e.offset, e.adu, e.kind, e.error) for e in streamed] == [
            (e.offset, e.adu, e.kind, e.error) for e in bulk
        ]
    assert sum(1 for f in bulk if f.error) == 6


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty file"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "not a pyrtu capture"),
        (bytes(range(11, 256)) * 40, "no header line"),
        (
            b"PYRTUCAP 1 baudrate=x bytesize=8 parity=E stopbits=1 bits=11 char_ns=5 drops=2\n",
            "baudrate='x' is not 1..100000000",
        ),
        (b"PYRTUCAP 1 parity=Q\n", "parity='Q' is not N, E or O"),
        (b"PYRTUCAP 2 baudrate=9600\n", "unsupported capture version '2'"),
        (
            b"PYRTUCAP 1 baudrate=9600 bytesize=8 parity=E stopbits=1 bits=11\n",
            "lacks char_ns",
        ),
        (b"PYRTUCAP\xff 1\n", "not text"),
        (b"hello world\n", "does not start with PYRTUCAP"),
    ],
)
def test_a_file_that_is_not_a_capture(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.cap"
    path.write_bytes(content)
    with pytest.raises(CaptureError, match=message) as info:
        CaptureReader(str(path))
    assert str(path) in str(info.value)
    assert isinstance(info.value, ValueError)


def test_a_damaged_record_is_an_error_naming_its_offset(tmp_path: Path) -> None:
    path = tmp_path / "damaged.cap"
    write(path, [(0, 0, b"\x01\x02"), (100, 7, b"\x03")])  # a 3-drop bus has no drop 7
    header = len(capsynth.header().line())
    with pytest.raises(CaptureError, match=f"record at byte {header + 14} names drop 7"):
        list(capture_frames(str(path)))
    write(path, [(0, 0, b"\x01"), (-5, 1, b"\x02")])
    with pytest.raises(CaptureError, match="has the time -5 us"):
        load_capture(str(path))


def test_a_cut_last_record_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "cut.cap"
    write(path, [(0, 0, b"\x01\x02\x03"), (100_000, 1, b"\x04\x05\x06")])
    full = path.read_bytes()
    path.write_bytes(full[:-2])
    with CaptureReader(str(path)) as reader:
        assert [r.data for r in reader.records()] == [b"\x01\x02\x03"]
        assert reader.truncated is not None
        assert reader.truncated.present == RECORD.size + 1
        assert reader.truncated.expected == RECORD.size + 3
        assert "cut short" in str(reader.truncated)
    path.write_bytes(full[:-7])  # inside the record header
    assert load_capture(str(path)).truncated is not None
    path.write_bytes(full)
    assert load_capture(str(path)).truncated is None


def test_header_round_trip() -> None:
    h = capsynth.header(5)
    assert CaptureHeader.parse(h.line()) == h


MEMORY = textwrap.dedent(
    """
    import sys
    from pyrtu.vbus.capture import capture_frames
    n = sum(1 for _ in capture_frames(sys.argv[1], backend="c"))
    # this process's own peak (VmHWM, kB): getrusage's ru_maxrss would carry the
    # peak of the process it was forked from (Linux keeps it across exec)
    with open("/proc/self/status") as status:
        peak = next(line.split()[1] for line in status if line.startswith("VmHWM:"))
    print(n, peak)
    """
)
# Tens of megabytes through the pure-Python framer take minutes: the memory tests
# measure the reader with the C framer (the twin's framer buffers the same bounded way).
needs_c_core = needs_c(_backend.C is None)
# Under AddressSanitizer (make test-asan) the peak RSS is the sanitizer's (shadow
# memory, its allocator's caches and quarantine): there the memory tests stream the
# same captures through the instrumented core and check the frames, and the bounds
# are held by the plain build (make test).
SANITIZED = "ASAN_OPTIONS" in os.environ


def peak_rss(path: Path) -> tuple[int, int]:
    """(frames, peak RSS in kB) of streaming a capture in a fresh process."""
    out = subprocess.run(
        [sys.executable, "-c", MEMORY, str(path)],
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
        cwd=ROOT,
    ).stdout.split()
    return int(out[0]), int(out[1])


@needs_c_core
def test_memory_is_bounded_whatever_the_capture_size(tmp_path: Path) -> None:
    # Memory, not time: the 24 MB capture must take what the 3 MB one takes
    # (the old reader built a tuple per byte: 482 MB for 5 MB).
    sizes = {}
    for mb in (3, 24):
        path = tmp_path / f"valid{mb}.cap"
        with open(path, "wb") as f:
            frames = capsynth.write_valid(f, mb * 1_000_000, registers=125)
        got, rss = peak_rss(path)
        assert got == frames
        sizes[mb] = rss
        path.unlink()
    if not SANITIZED:
        assert sizes[24] < 150 * 1024, sizes
        assert sizes[24] < sizes[3] + 16 * 1024, sizes  # kB: independent of the size


@needs_c_core
def test_memory_is_bounded_on_random_bytes(tmp_path: Path) -> None:
    path = tmp_path / "noise.cap"
    with open(path, "wb") as f:
        capsynth.write_random_records(f, 5_000_000)
    got, rss = peak_rss(path)
    assert got > 0  # noise still frames the odd good CRC or a discard run
    if not SANITIZED:
        assert rss < 150 * 1024
    os.unlink(path)
