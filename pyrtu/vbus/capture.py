"""Capture files: every byte on the virtual wire with its time.

Format (version 1)
------------------

A capture starts with one ASCII header line ending in ``\\n``::

    PYRTUCAP 1 baudrate=9600 bytesize=8 parity=E stopbits=1 bits=11 char_ns=1145833
    drops=4 start_unix_ns=1700000000000000000

(shown on two lines here; it is one line in the file).

``bits`` is the number of bits per character used for timing (start + data +
parity + stop) and ``char_ns`` the character time in nanoseconds; unknown
``key=value`` fields must be ignored by readers.  Then binary records follow, all
little-endian::

    int64  t_us    start of the first character on the wire, in microseconds
                   since the capture started
    uint16 drop    the drop that transmitted; bit 15 set = these bytes were
                   corrupted by a collision (they are stored as receivers saw them)
    uint16 n       number of bytes
    n bytes        the bytes, back to back on the wire: byte k occupies
                   [t + k*char, t + (k+1)*char) and is received at t + (k+1)*char

A record is a run of characters one drop put on the wire back to back; a silence,
a lost byte (fault) or a change of the collision flag starts a new record.
Records are written when a run ends, so records of different drops can be out of
time order: readers sort bytes by their reception time (`read_capture` does).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import IO, Any

__all__ = [
    "MAGIC",
    "Capture",
    "CaptureHeader",
    "CaptureRecord",
    "CaptureWriter",
    "load_capture",
    "read_capture",
]

MAGIC = "PYRTUCAP"
VERSION = 1
RECORD = struct.Struct("<qHH")
COLLISION_FLAG = 0x8000
MAX_RUN = 0xFFFF


@dataclass(frozen=True)
class CaptureHeader:
    """The header line of a capture."""

    baudrate: int
    bytesize: int
    parity: str
    stopbits: int
    bits: int
    char_ns: int
    drops: int
    start_unix_ns: int
    version: int = VERSION

    def line(self) -> bytes:
        return (
            f"{MAGIC} {self.version} baudrate={self.baudrate} bytesize={self.bytesize}"
            f" parity={self.parity} stopbits={self.stopbits} bits={self.bits}"
            f" char_ns={self.char_ns} drops={self.drops}"
            f" start_unix_ns={self.start_unix_ns}\n"
        ).encode("ascii")

    @classmethod
    def parse(cls, line: bytes) -> CaptureHeader:
        words = line.decode("ascii").split()
        if len(words) < 2 or words[0] != MAGIC:
            raise ValueError("not a pyrtu capture (bad magic)")
        version = int(words[1])
        if version != VERSION:
            raise ValueError(f"unsupported capture version {version}")
        kv = dict(w.split("=", 1) for w in words[2:] if "=" in w)
        try:
            return cls(
                baudrate=int(kv["baudrate"]),
                bytesize=int(kv["bytesize"]),
                parity=kv["parity"],
                stopbits=int(kv["stopbits"]),
                bits=int(kv["bits"]),
                char_ns=int(kv["char_ns"]),
                drops=int(kv["drops"]),
                start_unix_ns=int(kv.get("start_unix_ns", "0")),
                version=version,
            )
        except KeyError as exc:
            raise ValueError(f"capture header lacks {exc.args[0]}") from None


@dataclass(frozen=True)
class CaptureRecord:
    """One record: bytes one drop put on the wire back to back from ``t_us``."""

    t_us: int
    drop: int
    collision: bool
    data: bytes

    def times(self, char_ns: int) -> list[float]:
        """Reception time (s, since capture start) of each byte."""
        t0 = self.t_us * 1000
        return [(t0 + (k + 1) * char_ns) / 1e9 for k in range(len(self.data))]


@dataclass(frozen=True)
class Capture:
    """A loaded capture: header, records, and the merged byte stream."""

    header: CaptureHeader
    records: tuple[CaptureRecord, ...]
    data: bytes
    times: tuple[float, ...]
    drops: tuple[int, ...]

    @property
    def chunks(self) -> list[tuple[int, float]]:
        """``[(offset, time_s), ...]`` for `parse_stream`, one entry per byte."""
        return list(enumerate(self.times))

    def parse_kwargs(self) -> dict[str, Any]:
        """The byte-format keywords of this capture, for `parse_stream`/`Framer`."""
        h = self.header
        return {
            "baudrate": h.baudrate,
            "parity": h.parity,
            "stopbits": h.stopbits,
            "bytesize": h.bytesize,
        }

    def parse(self, role: str = "monitor", **kwargs: Any) -> Sequence[Any]:
        """Decode the capture with ``pyrtu.parse_stream`` (monitor role by default)."""
        from .._backend import active as core

        options = self.parse_kwargs()
        options.update(kwargs)
        result: Sequence[Any] = core.parse_stream(
            self.data, role, times=list(self.times), **options
        )
        return result


def _read_records(f: IO[bytes]) -> tuple[CaptureHeader, list[CaptureRecord]]:
    header = CaptureHeader.parse(f.readline())
    records: list[CaptureRecord] = []
    while True:
        head = f.read(RECORD.size)
        if not head:
            break
        if len(head) < RECORD.size:
            break  # truncated tail (capture still being written, or cut): ignore
        t_us, drop, n = RECORD.unpack(head)
        data = f.read(n)
        if len(data) < n:
            break
        records.append(
            CaptureRecord(t_us, drop & ~COLLISION_FLAG, bool(drop & COLLISION_FLAG), data)
        )
    return header, records


def load_capture(path: str) -> Capture:
    """Read a capture file; bytes are merged in order of reception time."""
    with open(path, "rb") as f:
        header, records = _read_records(f)
    entries: list[tuple[int, int, int, int]] = []  # (rx_ns, seq, byte, drop)
    seq = 0
    for rec in records:
        t0 = rec.t_us * 1000
        for k, b in enumerate(rec.data):
            entries.append((t0 + (k + 1) * header.char_ns, seq, b, rec.drop))
            seq += 1
    entries.sort()
    return Capture(
        header=header,
        records=tuple(records),
        data=bytes(e[2] for e in entries),
        times=tuple(e[0] / 1e9 for e in entries),
        drops=tuple(e[3] for e in entries),
    )


def read_capture(path: str) -> tuple[bytes, list[tuple[int, float]]]:
    """Read a capture as ``(data, chunks)`` for ``pyrtu.parse_stream``.

    ``chunks`` is ``[(offset, time_s), ...]`` with one entry per byte (its
    reception time in seconds since the capture started)::

        data, chunks = read_capture(path)
        frames = pyrtu.parse_stream(data, "monitor", chunks=chunks, baudrate=9600)
    """
    cap = load_capture(path)
    return cap.data, cap.chunks


class CaptureWriter:
    """Writes runs of wire characters as capture records (used by the hub)."""

    def __init__(self, path: str, header: CaptureHeader) -> None:
        self.path = path
        self.header = header
        self._char_ns = header.char_ns
        self._f: IO[bytes] = open(path, "wb")
        self._f.write(header.line())
        self._f.flush()
        # per drop: [start_ns, next_start_ns, collision, bytearray]
        self._runs: dict[int, tuple[int, list[int], bool, bytearray]] = {}

    def add(self, drop: int, start_ns: int, byte: int, collision: bool) -> None:
        """A character of `drop` that occupied the wire from `start_ns` (since start)."""
        run = self._runs.get(drop)
        if run is not None:
            t0, nxt, coll, buf = run
            if nxt[0] == start_ns and coll == collision and len(buf) < MAX_RUN:
                buf.append(byte)
                nxt[0] = start_ns + self._char_ns
                return
            self._write(drop, t0, coll, buf)
        self._runs[drop] = (start_ns, [start_ns + self._char_ns], collision, bytearray((byte,)))

    def end_run(self, drop: int) -> None:
        """The drop's run cannot continue: write it out."""
        run = self._runs.pop(drop, None)
        if run is not None:
            self._write(drop, run[0], run[2], run[3])
            self._f.flush()

    def pending(self) -> list[int]:
        return list(self._runs)

    def _write(self, drop: int, start_ns: int, collision: bool, buf: bytearray) -> None:
        flag = COLLISION_FLAG if collision else 0
        self._f.write(RECORD.pack(round(start_ns / 1000), drop | flag, len(buf)))
        self._f.write(buf)

    def close(self) -> None:
        if self._f.closed:
            return
        for drop in list(self._runs):
            self.end_run(drop)
        self._f.close()
