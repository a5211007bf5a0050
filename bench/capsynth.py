"""Synthetic captures for tests and benchmarks: a master polling slaves on a
19200-baud 8E1 bus, written record by record as the hub writes them, in
constant memory whatever the size."""

from __future__ import annotations

import os
import struct
from typing import IO

from pyrtu.vbus.capture import RECORD, CaptureHeader

BAUD = 19200
BITS = 11
CHAR_NS = round(BITS * 1e9 / BAUD)


def header(drops: int = 3) -> CaptureHeader:
    return CaptureHeader(BAUD, 8, "E", 1, BITS, CHAR_NS, drops, 1_700_000_000_000_000_000)


def _crc(data: bytes) -> bytes:
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def _adu(pdu: bytes) -> bytes:
    return pdu + _crc(pdu)


def transactions(registers: int = 60) -> list[tuple[int, bytes]]:
    """One polling cycle: (drop, adu) for two slaves answering FC 03."""
    out = []
    for slave in (1, 2):
        req = _adu(bytes([slave, 3, 0, 0, 0, registers]))
        body = bytes(range(2 * registers))
        resp = _adu(bytes([slave, 3, 2 * registers]) + body)
        out += [(0, req), (slave, resp)]
    return out


def write_valid(f: IO[bytes], size: int, registers: int = 60) -> int:
    """Records of polling traffic (3.5+ characters of silence between frames) until
    the file holds ``size`` bytes; returns the number of frames."""
    f.write(header().line())
    cycle = transactions(registers)
    t_ns = 0
    gap_ns = 5 * CHAR_NS  # turnaround, more than t3.5
    written = f.tell()
    frames = 0
    parts: list[bytes] = []
    while written < size:
        for drop, adu in cycle:
            rec = RECORD.pack(t_ns // 1000, drop, len(adu)) + adu
            parts.append(rec)
            written += len(rec)
            t_ns += len(adu) * CHAR_NS + gap_ns
            frames += 1
        if len(parts) > 4096:
            f.write(b"".join(parts))
            parts.clear()
    f.write(b"".join(parts))
    return frames


def write_random_tail(f: IO[bytes], size: int) -> None:
    """A valid header followed by ``size`` random bytes (a damaged file)."""
    f.write(header().line())
    left = size
    while left > 0:
        n = min(left, 1 << 20)
        f.write(os.urandom(n))
        left -= n


def write_random_records(f: IO[bytes], size: int) -> None:
    """Well-formed records of random bytes (line noise): the parser's worst case."""
    f.write(header().line())
    t_ns = 0
    written = f.tell()
    while written < size:
        data = os.urandom(200)
        rec = RECORD.pack(t_ns // 1000, 0, len(data)) + data
        f.write(rec)
        written += len(rec)
        t_ns += (len(data) + 5) * CHAR_NS
