"""atheris harness for the bridge outbox's file format (issue 19): segment and cursor
files as a crash, a bad disk or a stray program could leave them.

    python fuzz/fuzz_outbox.py -max_total_time=60 build/fuzz/corpus/outbox

(atheris from PyPI: ``.venv/bin/python -m pip install atheris``, as ``make
fuzz-python`` does.)  The input is either raw bytes after a segment header, or a
recipe (a leading 0x00 byte) of records, each intact, bit-flipped, cut short, junk,
replayed with an old sequence number or after a gap, which reaches deeper than
random bytes do.  Invariants:

* `scan` of any bytes never raises; its items tile the segment; a valid item is
  byte for byte what `encode_record` writes for its (seq, time, payload), and the
  sequence numbers of valid items increase; a recipe's intact records are exactly
  the valid items.
* `decode_state` of any bytes returns None or a CursorState.
* `Outbox` opened on a directory (in /dev/shm) holding the bytes as a segment and a
  cursor file raises nothing but OutboxError (bad header), returns exactly the valid
  items above the ack cursor, and an append after them is read back.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import atheris

with atheris.instrument_imports():
    from pyrtu.outbox import _format as fmt
    from pyrtu.outbox.outbox import Outbox, OutboxError

SHM = "/dev/shm" if os.path.isdir("/dev/shm") else None
WORK = Path(tempfile.mkdtemp(prefix="fuzz-outbox-", dir=SHM))


def _recipe(fdp: Any) -> tuple[bytes, list[tuple[int, bytes]]]:
    """A segment of intact and damaged records, and the intact ones."""
    data = bytearray(fmt.segment_header(1))
    intact: list[tuple[int, bytes]] = []
    seq = 1
    for _ in range(fdp.ConsumeIntInRange(0, 24)):
        kind = fdp.ConsumeIntInRange(0, 5)
        body = fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 80))
        if kind == 3:  # junk
            data += body
            continue
        if kind == 4:  # a gap in the numbers
            seq += fdp.ConsumeIntInRange(1, 1000)
            continue
        if kind == 5:  # checksum right, number not above the last valid one
            data += fmt.encode_record(intact[-1][0] if intact else 0, 0.0, body)
            continue
        rec = bytearray(fmt.encode_record(seq, float(seq), body))
        if kind == 1:
            rec[fdp.ConsumeIntInRange(0, len(rec) - 1)] ^= fdp.ConsumeIntInRange(1, 255)
        elif kind == 2:
            at = fdp.ConsumeIntInRange(0, len(rec) - 1)
            rec[at:] = bytes([rec[at] ^ 0xFF])  # cut short: what follows cannot complete it
        else:
            intact.append((seq, body))
        data += rec
        seq += 1
    return bytes(data), intact


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    recipe = fdp.ConsumeIntInRange(0, 1) == 0
    state = fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 600))
    intact: list[tuple[int, bytes]] | None = None
    if recipe:
        seg, intact = _recipe(fdp)
    else:
        seg = fmt.segment_header(1) + fdp.ConsumeBytes(fdp.remaining_bytes())
    items = list(fmt.scan(lambda off, n: seg[off : off + n], 16, len(seg), last_seq=0, chunk=64))
    pos, last = 16, 0
    for it in items:
        assert it.off == pos and it.end > it.off, (it, pos)
        if it.seq >= 0:
            assert it.payload is not None and it.seq > last
            assert seg[it.off : it.end] == fmt.encode_record(it.seq, it.time, it.payload)
            last = it.seq
        pos = it.end
    assert pos == len(seg)
    valid = [(it.seq, it.payload) for it in items if it.seq >= 0]
    if intact is not None:
        assert valid == intact, (valid, intact)
    decoded = fmt.decode_state(state)
    assert decoded is None or isinstance(decoded, fmt.CursorState)

    d = WORK / "ob"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    (d / fmt.segment_name(1)).write_bytes(seg)
    (d / "cursor").write_bytes(state)
    try:
        ob = Outbox(d)
    except OutboxError:
        raise  # the header is always right here: nothing else may refuse the files
    with ob:
        got: list[tuple[int, bytes]] = []
        while batch := ob.pending(50, after=got[-1][0] if got else None):
            got += batch
        assert got == [r for r in valid if r[0] > ob.acked], (got, valid, ob.acked)
        assert ob.depth == len(got)
        seq = ob.append(b"after", 1.0)
        assert seq > max([s for s, _ in valid] + [ob.acked])
        ob.flush()
        assert ob.pending(1, after=seq - 1) == [(seq, b"after")]


def main() -> None:
    atheris.Setup(sys.argv, test_one_input)
    try:
        atheris.Fuzz()
    finally:
        shutil.rmtree(WORK, ignore_errors=True)


if __name__ == "__main__":
    main()
