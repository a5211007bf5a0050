"""The image of a DataStore in pure Python: the twin of csrc/rtu_image.c.

A server answers plain reads from it without its slave's Python: MODBUS Application
Protocol V1.1b3, 6.1-6.4 (FC 01 Read Coils and 02 Read Discrete Inputs: quantity
1..2000, byte count ceil(quantity / 8), bits LSB first, unused high bits 0; FC 03 Read
Holding Registers and 04 Read Input Registers: quantity 1..125, byte count 2 x
quantity, registers big-endian).  Anything else is deferred (None): the slave answers
it, exceptions included.

``tables``: four sequences (coils, discrete inputs, holding registers, input
registers; FC 01..04 read them in that order), each of ``(start, flags, values)``
ranges sorted by start, not overlapping; ``flags`` `PLAIN` (the image answers its
values) or `HELD` (its reads are the slave's: an ``on_read`` callback).  A bit is
any value, nonzero reading as 1.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

COILS = 0
DISCRETE_INPUTS = 1
HOLDING_REGISTERS = 2
INPUT_REGISTERS = 3
TABLES = 4

PLAIN = 0
HELD = 1

ADDRESSES = 0x10000
#: [AP] 6.1-6.4: the largest quantity of a read, by function code
MAX_QUANTITY = {1: 2000, 2: 2000, 3: 125, 4: 125}

ImageRange = tuple[int, int, Sequence[int]]
Tables = Sequence[Sequence[ImageRange]]


def image_check(tables: Tables) -> bool:
    """As rtu_image_check: four tables of ranges each with 1..65536 values, start
    0..65535 and start + count <= 65536, known flags, sorted and not overlapping;
    and values a uint16_t holds (ints 0..65535)."""
    if len(tables) != TABLES:
        return False
    for ranges in tables:
        nxt = 0
        for i, (start, flags, values) in enumerate(ranges):
            count = len(values)
            if count == 0 or not 0 <= start < ADDRESSES or start + count > ADDRESSES:
                return False
            if flags not in (PLAIN, HELD) or (i > 0 and start < nxt):
                return False
            if any(not isinstance(v, int) or not 0 <= v <= 0xFFFF for v in values):
                return False
            nxt = start + count
    return True


def image_answer(tables: Tables, pdu: bytes) -> bytes | None:
    """The response PDU of ``pdu`` from a checked image (`image_check`), or None:
    Python answers it (as rtu_image_answer's RTU_IMAGE_DEFER)."""
    if len(pdu) != 5 or not 1 <= pdu[0] <= 4:
        return None
    fc = pdu[0]
    address = pdu[1] << 8 | pdu[2]
    quantity = pdu[3] << 8 | pdu[4]
    end = address + quantity
    if not 1 <= quantity <= MAX_QUANTITY[fc] or end > ADDRESSES:
        return None
    ranges = tables[fc - 1]
    i = bisect.bisect_right(ranges, address, key=lambda r: r[0]) - 1
    if i < 0:
        return None
    values: list[int] = []
    pos = address
    while pos < end:
        if i >= len(ranges):
            return None
        start, flags, vals = ranges[i]
        if not start <= pos < start + len(vals) or flags != PLAIN:
            return None
        stop = min(end, start + len(vals))
        values += vals[pos - start : stop - start]
        pos = stop
        i += 1
    if fc <= 2:
        packed = bytearray((quantity + 7) // 8)
        for k, v in enumerate(values):
            if v:
                packed[k >> 3] |= 1 << (k & 7)
        return bytes((fc, len(packed))) + bytes(packed)
    return bytes((fc, 2 * quantity)) + b"".join(v.to_bytes(2, "big") for v in values)
