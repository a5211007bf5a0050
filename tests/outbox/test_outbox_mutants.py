"""The outbox's budget at its exact boundary (found untested by the mutation run,
docs/MUTATION.md): with drop-oldest, a record that needs exactly the room of the
oldest segment drops that one segment, not two.  Sizes from the format
(pyrtu/outbox/_format.py: a 16-byte segment header, a 28-byte record
header)."""

from __future__ import annotations

from pathlib import Path

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
