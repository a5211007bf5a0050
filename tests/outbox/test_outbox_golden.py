"""The outbox's on-disk format, pinned by golden files (tests/outbox/data/README.md).

An outbox directory written once by the format-1 writer is read back to the records
written literally here (an upgrade can read an older outbox); the current writer
produces the same bytes for the same input (a change of the format fails here, not
in the field); and an outbox of an unknown, newer format version is refused with a
message that says so, touching nothing.
"""

from __future__ import annotations

import shutil
import struct
import zlib
from pathlib import Path

import pytest
from outbox_helpers import everything

from pyrtu.outbox.outbox import Outbox, OutboxError, OutboxLimits

GOLDEN = Path(__file__).parent / "data" / "v1"
FILES = ["00000000000000000006.seg", "00000000000000000011.seg", "cursor"]

#: what the golden directory holds: records 6..12 (1..5 were acknowledged), as written
EXPECTED = [
    (6, b"\x06" * 156),
    (7, b"\x07" * 157),
    (8, b"\x08" * 158),
    (9, b"\x09" * 159),
    (10, b"\x0a" * 160),
    (11, b"\x0b" * 161),
    (12, b"\x0c" * 162),
]


def write_reference(directory: Path) -> None:
    """The input the golden files were written with (README.md)."""
    with Outbox(directory, OutboxLimits(max_bytes=1 << 20, segment_bytes=1024)) as ob:
        for i in range(1, 13):
            ob.append(bytes([i]) * (150 + i), 1_800_000_000.0 + i / 4)
        ob.flush()
        ob.ack(5)
        ob.flush()


def copy_golden(tmp_path: Path) -> Path:
    d = tmp_path / "ob"
    shutil.copytree(GOLDEN, d)
    return d


def test_the_golden_files_are_there() -> None:
    assert sorted(p.name for p in GOLDEN.iterdir()) == FILES


def test_an_outbox_of_format_1_is_read_back(tmp_path: Path) -> None:
    d = copy_golden(tmp_path)
    with Outbox(d) as ob:
        assert everything(ob) == EXPECTED
        assert ob.acked == 5 and ob.depth == 7 and ob.dropped == 0
        assert ob.oldest_time == 1_800_000_000.0 + 6 / 4  # record 6's
        assert ob.corrupt == 0
        # numbers are never reused: the next is past every number handed out
        seq = ob.append(b"after the upgrade", 1_900_000_000.0)
        assert seq == 13
        ob.flush()
    with Outbox(d) as again:
        assert everything(again) == [*EXPECTED, (13, b"after the upgrade")]


def test_the_golden_files_decode_by_the_documented_layout() -> None:
    """The layout of _format's docstring, read with struct alone."""
    seg = (GOLDEN / FILES[0]).read_bytes()
    assert seg[:16] == b"pyrtuOB\x01" + struct.pack("<Q", 6)
    off, records = 16, []
    while off < len(seg):
        magic, length, seq, when, crc = struct.unpack_from("<4sIQdI", seg, off)
        payload = seg[off + 28 : off + 28 + length]
        assert magic == b"\xb7OBr"
        assert crc == zlib.crc32(payload, zlib.crc32(seg[off : off + 24]))
        assert when == 1_800_000_000.0 + seq / 4
        records.append((seq, payload))
        off += 28 + length
    assert off == len(seg) and records == EXPECTED[:5]
    cursor = (GOLDEN / "cursor").read_bytes()
    assert len(cursor) == 512 + 40
    slots = []
    for at in (0, 512):  # two 40-byte slots, in different sectors
        body = cursor[at : at + 36]
        assert struct.unpack_from("<I", cursor, at + 36)[0] == zlib.crc32(body)
        slots.append(struct.unpack("<4sQQQQ", body))
    newest = max(slots, key=lambda s: s[1])
    assert newest[0] == b"OBc1" and newest[2] == 5 and newest[4] == 0  # acked 5, none dropped


def test_the_writer_produces_the_golden_bytes(tmp_path: Path) -> None:
    """Byte for byte: a change of the record header, the magic, the cursor's slots or
    the segment naming makes this fail (see README.md before touching anything)."""
    d = tmp_path / "ob"
    write_reference(d)
    written = sorted(p.name for p in d.iterdir() if p.name != "lock")
    assert written == FILES
    for name in FILES:
        assert (d / name).read_bytes() == (GOLDEN / name).read_bytes(), name


def _newer_segment(d: Path) -> None:
    path = d / FILES[0]
    data = bytearray(path.read_bytes())
    data[7] = 2  # the segment magic's version byte
    path.write_bytes(bytes(data))


def _newer_cursor(d: Path) -> None:
    path = d / "cursor"
    data = bytearray(path.read_bytes())
    for at in (0, 512):
        data[at + 3 : at + 4] = b"2"  # OBc1 -> OBc2, its checksum made right
        data[at + 36 : at + 40] = struct.pack("<I", zlib.crc32(bytes(data[at : at + 36])))
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(("make", "what"), [(_newer_segment, FILES[0]), (_newer_cursor, "cursor")])
def test_a_newer_format_version_is_refused_clearly(tmp_path: Path, make: object, what: str) -> None:
    d = copy_golden(tmp_path)
    make(d)  # type: ignore[operator]
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    with pytest.raises(OutboxError) as e:
        Outbox(d)
    message = str(e.value)
    assert what in message and "format version 2" in message and "version 1" in message
    assert str(d) in message
    after = {p.name: p.read_bytes() for p in d.iterdir() if p.name != "lock"}
    assert after == {k: v for k, v in before.items() if k != "lock"}  # nothing touched
