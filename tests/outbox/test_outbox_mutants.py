"""The outbox where the mutation run (docs/MUTATION.md) found it untested: the
budget at its exact boundary (with drop-oldest, a record that needs exactly the
room of the oldest segment drops that one segment, not two), a record found at the
very start of a chunk when resynchronising, and the largest sequence number.
Sizes from the format (pyrtu/outbox/_format.py: a 16-byte segment header, a
28-byte record header)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

from pyrtu.outbox import _format as fmt
from pyrtu.outbox.outbox import Outbox, OutboxLimits

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
