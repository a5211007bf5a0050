"""The outbox's on-disk format: segment files of checksummed records, and the cursor file.

Pure encoding, decoding and scanning; the `Outbox` (outbox.py) does the I/O around it.

A segment file is named by the sequence number of its first record, ``%020d.seg``, and
holds a 16-byte header (``SEG_MAGIC``, first sequence, little-endian u64) followed by
records.  A record is a 28-byte header and the payload::

    magic  b"\\xb7OBr"   4 bytes
    length u32          payload bytes
    seq    u64          sequence number (strictly increasing through the outbox)
    time   float64      the `now` given to append()
    crc    u32          CRC-32 (zlib) of the 24 bytes above followed by the payload

The cursor file holds two 40-byte slots (at offsets 0 and 512, in different sectors, so
that a write torn by a power cut spoils at most the slot being written)::

    magic b"OBc1", generation u64, acked u64, reserved u64, dropped u64, crc u32

The slot with the highest generation and a valid checksum wins.

The format's version is the segment magic's last byte and the cursor magic's last
character (``FORMAT_VERSION``); an outbox of another version is refused
(`foreign_version`), never read as corrupt nor written over.  ``acked``: every
record with a sequence number <= acked is delivered (or dropped).  ``reserved``: every
sequence number handed out so far is < reserved, so numbers are never reused after a
crash.  ``dropped``: records dropped by the budget since the directory was created.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Callable, Iterator
from typing import NamedTuple

FORMAT_VERSION = 1
SEG_MAGIC = b"pyrtuOB\x01"
SEG_HEAD = struct.Struct("<8sQ")
REC_MAGIC = b"\xb7OBr"
REC_PRE = struct.Struct("<4sIQd")  # the part of the header the checksum covers first
REC_HEAD = struct.Struct("<4sIQdI")
CRC = struct.Struct("<I")
STATE_MAGIC = b"OBc1"
STATE = struct.Struct("<4sQQQQ")
STATE_SLOTS = (0, 512)
STATE_SIZE = STATE_SLOTS[1] + STATE.size + CRC.size
SEGMENT_NAME = re.compile(r"^(\d{20})\.seg$")
MAX_SEQ = 2**63 - 1

assert REC_HEAD.size == 28 and SEG_HEAD.size == 16 and REC_PRE.size == 24


def cursor_version(data: bytes) -> int:
    """The newest format version named by a cursor slot with a valid checksum
    (``FORMAT_VERSION`` when none is valid: an empty or torn cursor)."""
    found: list[int] = []
    for off in STATE_SLOTS:
        end = off + STATE.size
        if len(data) < end + CRC.size:
            continue
        if zlib.crc32(data[off:end]) != CRC.unpack_from(data, end)[0]:
            continue
        magic = data[off : off + len(STATE_MAGIC)]
        if magic[:-1] == STATE_MAGIC[:-1]:
            found.append(magic[-1] - ord("0"))
    return max(found, default=FORMAT_VERSION)


def segment_version(head: bytes) -> int:
    """The format version a segment header names (``FORMAT_VERSION`` when it is no
    outbox segment header at all: that is for the recovery to report)."""
    prefix = SEG_MAGIC[:-1]
    if len(head) < SEG_HEAD.size or head[: len(prefix)] != prefix:
        return FORMAT_VERSION
    return head[len(prefix)]


def segment_name(first: int) -> str:
    return f"{first:020d}.seg"


def segment_header(first: int) -> bytes:
    return SEG_HEAD.pack(SEG_MAGIC, first)


def parse_segment_header(data: bytes) -> int | None:
    """The first sequence number a segment header names, None if it is not one."""
    if len(data) < SEG_HEAD.size:
        return None
    magic, first = SEG_HEAD.unpack_from(data)
    return int(first) if magic == SEG_MAGIC else None


def encode_record(seq: int, now: float, payload: bytes) -> bytes:
    pre = REC_PRE.pack(REC_MAGIC, len(payload), seq, now)
    return pre + CRC.pack(zlib.crc32(payload, zlib.crc32(pre))) + payload


class CursorState(NamedTuple):
    """What a slot of the cursor file holds (``gen``, ``acked``, ``reserved``,
    ``dropped``: see the module docstring)."""

    gen: int
    acked: int
    reserved: int
    dropped: int


def encode_state(state: CursorState) -> tuple[int, bytes]:
    """(file offset, bytes) of the slot this generation is written to."""
    body = STATE.pack(STATE_MAGIC, *state)
    return STATE_SLOTS[state.gen % 2], body + CRC.pack(zlib.crc32(body))


def decode_state(data: bytes) -> CursorState | None:
    """The newest valid slot of a cursor file's contents, None if neither is valid."""
    best: CursorState | None = None
    for off in STATE_SLOTS:
        end = off + STATE.size
        if len(data) < end + CRC.size:
            continue
        (crc,) = CRC.unpack_from(data, end)
        if zlib.crc32(data[off:end]) != crc:
            continue
        magic, *fields = STATE.unpack_from(data, off)
        if magic != STATE_MAGIC:
            continue
        state = CursorState(*fields)
        if max(state) > MAX_SEQ:  # no number this format writes is that large
            continue
        if best is None or state.gen > best.gen:
            best = state
    return best


class Item(NamedTuple):
    """One stretch of a segment: a valid record (seq >= 0) or a bad region (seq == -1)."""

    off: int
    end: int
    seq: int
    time: float
    payload: bytes | None


class _Chunks:
    """A byte range [.., end) of one file, read in bounded chunks through `read`."""

    def __init__(self, read: Callable[[int, int], bytes], end: int, chunk: int) -> None:
        self.read = read
        self.end = end
        self.chunk = chunk
        self.buf = b""
        self.base = 0

    def view(self, off: int, n: int) -> tuple[bytes, int] | None:
        """(buffer, index) such that buffer[index:index + n] are the n bytes at `off`."""
        if off + n > self.end:
            return None
        if off < self.base or off + n > self.base + len(self.buf):
            size = min(max(self.chunk, n), self.end - off)
            self.buf = self.read(off, size)
            self.base = off
            if len(self.buf) < n:  # the file is shorter than we were told
                self.end = off + len(self.buf)
                return None
        return self.buf, off - self.base

    def find(self, pattern: bytes, off: int) -> int:
        """The offset of the next `pattern` at or after `off`, -1 if none before end."""
        k = len(pattern)
        while off + k <= self.end:
            v = self.view(off, min(self.chunk, self.end - off))
            if v is None:  # the file is shorter than we were told: `end` is its end
                continue  # now (strictly lower), and the bytes it has are searched
            buf, i = v
            n = min(self.chunk, self.end - off)
            j = buf.find(pattern, i, i + n)
            if j >= 0:
                return off + (j - i)
            if off + n >= self.end:
                return -1
            off += n - (k - 1)
        return -1


def _record_at(ch: _Chunks, off: int, last_seq: int, max_seq: int) -> Item | None:
    v = ch.view(off, REC_HEAD.size)
    if v is None:
        return None
    buf, i = v
    magic, n, seq, t, crc = REC_HEAD.unpack_from(buf, i)
    if magic != REC_MAGIC or not last_seq < seq <= max_seq:
        return None
    pre = buf[i : i + REC_PRE.size]
    start = off + REC_HEAD.size
    v = ch.view(start, n)
    if v is None:
        return None
    buf, j = v
    payload = buf[j : j + n]
    if zlib.crc32(payload, zlib.crc32(pre)) != crc:
        return None
    return Item(off, start + n, seq, t, payload)


def scan(
    read: Callable[[int, int], bytes],
    start: int,
    end: int,
    *,
    last_seq: int,
    max_seq: int = MAX_SEQ,
    chunk: int = 1 << 18,
) -> Iterator[Item]:
    """The records of [start, end) in file order, and the bad regions between them.

    A record is valid when its magic and checksum are right, it ends by `end` and
    its sequence number is above the previous one (`last_seq` to begin with) and
    <= `max_seq`.
    After a bad record the scan resynchronises at the next offset where a valid
    record starts; a bad region running to `end` is a torn tail.
    """
    ch = _Chunks(read, end, chunk)
    off = start
    while off < ch.end:
        item = _record_at(ch, off, last_seq, max_seq)
        if item is not None:
            yield item
            last_seq = item.seq
            off = item.end
            continue
        cand = off
        while True:
            cand = ch.find(REC_MAGIC, cand + 1)
            if cand < 0:  # a bad region to the end: a torn tail, to where the file
                ch.view(off, ch.end - off)  # ends if it is shorter than we were told
                if ch.end > off:  # (none if it ends here)
                    yield Item(off, ch.end, -1, 0.0, None)
                return
            if _record_at(ch, cand, last_seq, max_seq) is not None:
                break
        yield Item(off, cand, -1, 0.0, None)
        off = cand


__all__ = [
    "CRC",
    "FORMAT_VERSION",
    "MAX_SEQ",
    "REC_HEAD",
    "REC_MAGIC",
    "REC_PRE",
    "SEGMENT_NAME",
    "SEG_HEAD",
    "SEG_MAGIC",
    "STATE",
    "STATE_MAGIC",
    "STATE_SIZE",
    "STATE_SLOTS",
    "CursorState",
    "Item",
    "cursor_version",
    "decode_state",
    "encode_record",
    "encode_state",
    "parse_segment_header",
    "scan",
    "segment_header",
    "segment_name",
    "segment_version",
]
