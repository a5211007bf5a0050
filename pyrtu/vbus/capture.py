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

Reading
-------

Everything here streams: `CaptureReader` reads the file in blocks of `BLOCK` bytes
and merges the records into reception order through a bounded reordering window
(a run is at most `MAX_RUN` characters long, so no record can start more than
`MAX_RUN` character times before one already read); `capture_frames` feeds the
merged runs to the sans-I/O `Framer`, so decoding a capture of any size takes
memory bounded by a constant (bench/bench_capture.py measures it).  `load_capture`
and `read_capture` return the whole byte stream for `parse_stream`: one byte per
byte, times and drops in arrays, one chunk per run of back-to-back bytes.

A file that is not a capture, or is damaged (a record naming a drop the bus does
not have, or a time before the start or more than 30 years after it), raises
`CaptureError` (a `ValueError`) naming the file and the byte offset.  A last record
cut short (the capture was still being written, or the file was truncated) is not
an error: `CaptureReader.truncated` tells, and ``pyrtu sniff`` warns.
"""

from __future__ import annotations

import heapq
import struct
from array import array
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import IO, Any

from pyrtu.core._backend import backend as _backend_named

__all__ = [
    "MAGIC",
    "Capture",
    "CaptureError",
    "CaptureHeader",
    "CaptureReader",
    "CaptureRecord",
    "CaptureWriter",
    "Truncation",
    "capture_frames",
    "load_capture",
    "read_capture",
    "stream_frames",
]

MAGIC = "PYRTUCAP"
VERSION = 1
RECORD = struct.Struct("<qHH")
COLLISION_FLAG = 0x8000
MAX_RUN = 0xFFFF
#: bytes read from the file at a time
BLOCK = 1 << 20
#: the header line is short; a longer first line is not a capture
MAX_HEADER = 4096
#: a record time beyond this (about 31.7 years, in microseconds) is damage
MAX_T_US = 10**15
#: the reordering window holds at most this many bytes / records (a damaged or
#: foreign file cannot make it grow further: what exceeds is merged as it comes)
MAX_PENDING_BYTES = 8 << 20
MAX_PENDING_RECORDS = 1 << 17


class CaptureError(ValueError):
    """A file that is not a readable pyrtu capture; the message names the file."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}")
        self.path = path


def _field(
    path: str, kv: dict[str, str], key: str, low: int, high: int, default: str | None = None
) -> int:
    text = kv.get(key, default)
    if text is None:
        raise CaptureError(path, f"not a valid pyrtu capture: the header lacks {key}=")
    try:
        value = int(text)
    except ValueError:
        value = low - 1
    if not low <= value <= high:
        raise CaptureError(
            path, f"not a valid pyrtu capture: header field {key}={text!r} is not {low}..{high}"
        )
    return value


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
    def parse(cls, line: bytes, path: str = "capture") -> CaptureHeader:
        """The header from its line; `CaptureError` says what is wrong with it."""
        if not line:
            raise CaptureError(path, "empty file (not a pyrtu capture)")
        if not line.endswith(b"\n"):
            raise CaptureError(path, "not a pyrtu capture (no header line)")
        try:
            words = line.decode("ascii").split()
        except UnicodeDecodeError:
            raise CaptureError(path, "not a pyrtu capture (the header is not text)") from None
        if len(words) < 2 or words[0] != MAGIC:
            raise CaptureError(path, f"not a pyrtu capture (it does not start with {MAGIC})")
        if words[1] != str(VERSION):
            raise CaptureError(
                path, f"unsupported capture version {words[1][:20]!r} (this pyrtu reads {VERSION})"
            )
        kv = dict(w.split("=", 1) for w in words[2:] if "=" in w)
        parity = kv.get("parity", "")
        if parity not in ("N", "E", "O"):
            raise CaptureError(
                path,
                f"not a valid pyrtu capture: header field parity={parity[:20]!r} is not N, E or O",
            )
        return cls(
            baudrate=_field(path, kv, "baudrate", 1, 100_000_000),
            bytesize=_field(path, kv, "bytesize", 5, 8),
            parity=parity,
            stopbits=_field(path, kv, "stopbits", 1, 2),
            bits=_field(path, kv, "bits", 7, 12),
            char_ns=_field(path, kv, "char_ns", 1, 10**10),
            drops=_field(path, kv, "drops", 1, 0x7FFF),
            start_unix_ns=_field(path, kv, "start_unix_ns", 0, 2**63 - 1, "0"),
            version=VERSION,
        )


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
class Truncation:
    """A last record cut short: where it starts and how much of it is there."""

    offset: int
    present: int
    expected: int

    def __str__(self) -> str:
        return (
            f"the last record (at byte {self.offset}) is cut short: {self.present} of"
            f" {self.expected} bytes; it is ignored"
        )


#: A run of back-to-back bytes in reception order: (data, reception time of its
#: first byte in ns since the capture started, drop).
Segment = tuple[bytes, int, int]


class CaptureReader:
    """A capture file opened for streaming: the header, then records or runs.

    Use as a context manager, or call `close`.  Iterate `records` (file order) or
    `segments` (reception order, merged); either reads the file once, in blocks.
    After the iteration: `truncated` (a `Truncation` or None), `late` (runs that
    came after later bytes were merged: only in damaged or foreign files).
    """

    def __init__(self, path: str) -> None:
        self.path = str(path)
        self._f: IO[bytes] = open(self.path, "rb")
        try:
            self.header = CaptureHeader.parse(self._f.readline(MAX_HEADER), self.path)
        except BaseException:
            self._f.close()
            raise
        self._offset = self._f.tell()
        self.truncated: Truncation | None = None
        self.late = 0
        self.records_read = 0

    def __enter__(self) -> CaptureReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    def records(self) -> Iterator[CaptureRecord]:
        """The records in file order (`CaptureError` at a damaged one)."""
        f = self._f
        drops = self.header.drops
        buf = b""
        pos = 0
        offset = self._offset  # file offset of buf[0]
        eof = False
        size = RECORD.size
        while True:
            if len(buf) - pos < size + MAX_RUN and not eof:
                more = f.read(BLOCK)
                eof = not more
                buf = buf[pos:] + more
                offset += pos
                pos = 0
            if len(buf) - pos < size:
                if len(buf) > pos:
                    self.truncated = Truncation(offset + pos, len(buf) - pos, size)
                return
            t_us, drop, n = RECORD.unpack_from(buf, pos)
            index = drop & ~COLLISION_FLAG
            if index >= drops or not 0 <= t_us <= MAX_T_US:
                what = (
                    f"names drop {index} of a {drops}-drop bus"
                    if index >= drops
                    else f"has the time {t_us} us"
                )
                raise CaptureError(
                    self.path,
                    f"damaged: the record at byte {offset + pos} {what}"
                    f" ({self.records_read} records read before it)",
                )
            end = pos + size + n
            if end > len(buf):
                if eof:
                    self.truncated = Truncation(offset + pos, len(buf) - pos, size + n)
                    return
                continue  # the block ends inside the record: read on
            data = buf[pos + size : end]
            pos = end
            self.records_read += 1
            yield CaptureRecord(t_us, index, bool(drop & COLLISION_FLAG), data)

    def segments(self) -> Iterator[Segment]:
        """Runs of bytes in order of reception time, merged across drops.

        Records of different drops that overlap in time (a collision) are
        interleaved byte by byte, ties in file order, as a sort of every byte by
        (reception time, file position) would; memory stays bounded.
        """
        char = self.header.char_ns
        window = (MAX_RUN + 64) * char
        heap: list[tuple[int, int, int, bytes, int]] = []  # (rx0, seq, start, data, drop)
        pending = 0
        latest = -(2**63)
        last_rx = -(2**63)
        seq = 0
        for rec in self.records():
            if not rec.data:
                continue
            start = rec.t_us * 1000
            heapq.heappush(heap, (start + char, seq, start, rec.data, rec.drop))
            seq += 1
            pending += len(rec.data)
            latest = max(latest, start)
            while heap and (
                heap[0][0] < latest - window
                or pending > MAX_PENDING_BYTES
                or len(heap) > MAX_PENDING_RECORDS
            ):
                seg = self._pop(heap, char)
                pending -= len(seg[0])
                if seg[1] < last_rx:
                    self.late += 1
                last_rx = seg[1] + (len(seg[0]) - 1) * char
                yield seg
        while heap:
            seg = self._pop(heap, char)
            if seg[1] < last_rx:
                self.late += 1
            last_rx = seg[1] + (len(seg[0]) - 1) * char
            yield seg

    @staticmethod
    def _pop(heap: list[tuple[int, int, int, bytes, int]], char: int) -> Segment:
        rx0, seq, start, data, drop = heapq.heappop(heap)
        if heap:
            nrx0, nseq = heap[0][0], heap[0][1]
            # bytes k with (start + (k+1)*char, seq) < (nrx0, nseq) come first
            m = (nrx0 - start - 1) // char
            if seq < nseq and (nrx0 - start) % char == 0:
                m += 1
            m = max(m, 1)
            if m < len(data):
                rest = start + m * char
                heapq.heappush(heap, (rest + char, seq, rest, data[m:], drop))
                data = data[:m]
        return data, rx0, drop


@dataclass
class Capture:
    """A capture loaded whole: header, the merged byte stream and, per byte, its
    reception time (s since the capture started) and drop, in arrays.

    `chunks` gives `parse_stream` one chunk per run of back-to-back bytes.  Use
    `capture_frames` (it streams) for files too big to hold.
    """

    header: CaptureHeader
    data: bytes
    times: array[float]
    drops: array[int]
    path: str = ""
    truncated: Truncation | None = None
    #: (offset, time of the run's last byte in s) per run
    _runs: Sequence[tuple[int, float]] = ()

    @property
    def records(self) -> tuple[CaptureRecord, ...]:
        """The records in file order (read again from the file: one object per record)."""
        with CaptureReader(self.path) as reader:
            return tuple(reader.records())

    @property
    def chunks(self) -> list[tuple[int, float]]:
        """``[(offset, time_s), ...]`` for `parse_stream`: one per run of back-to-back
        bytes, the time of its last byte (parse_stream spreads the others back at the
        character time)."""
        return list(self._runs)

    def parse_kwargs(self) -> dict[str, Any]:
        """The byte-format keywords of this capture, for `parse_stream`/`Framer`."""
        return _format(self.header)

    def parse(
        self, role: str = "monitor", *, backend: str | None = None, **kwargs: Any
    ) -> Sequence[Any]:
        """Decode the capture with `parse_stream` (monitor role by default; ``backend``
        "c" or "python", None: the active one)."""
        options = self.parse_kwargs()
        options.update(kwargs)
        core = _backend_named(backend)
        result: Sequence[Any] = core.parse_stream(self.data, role, chunks=self.chunks, **options)
        return result


def _format(h: CaptureHeader) -> dict[str, Any]:
    return {
        "baudrate": h.baudrate,
        "parity": h.parity,
        "stopbits": h.stopbits,
        "bytesize": h.bytesize,
    }


def load_capture(path: str) -> Capture:
    """Read a whole capture; bytes are merged in order of reception time.

    Memory: about 11 bytes per captured byte (the byte, its time, its drop) plus
    one tuple per run; `capture_frames` streams instead.
    """
    data = bytearray()
    times = array("d")
    drops = array("H")
    runs: list[tuple[int, float]] = []
    with CaptureReader(path) as reader:
        char = reader.header.char_ns
        for seg, rx0, drop in reader.segments():
            n = len(seg)
            runs.append((len(data), (rx0 + (n - 1) * char) / 1e9))
            data += seg
            times.extend((rx0 + k * char) / 1e9 for k in range(n))
            drops.extend(array("H", (drop,)) * n)
        truncated = reader.truncated
        header = reader.header
    return Capture(header, bytes(data), times, drops, str(path), truncated, runs)


def read_capture(path: str) -> tuple[bytes, list[tuple[int, float]]]:
    """Read a capture as ``(data, chunks)`` for ``pyrtu.parse_stream``.

    ``chunks`` is ``[(offset, time_s), ...]``, one entry per run of back-to-back
    bytes with the reception time (s since the capture started) of its last byte::

        data, chunks = read_capture(path)
        frames = pyrtu.parse_stream(data, "monitor", chunks=chunks, baudrate=9600)
    """
    cap = load_capture(path)
    return cap.data, cap.chunks


#: contiguous discard events are joined into runs of at most this many bytes
MAX_DISCARD_RUN = 1 << 16


def _join_discards(events: Iterator[Any]) -> Iterator[Any]:
    """Contiguous discard events as one run with the first one's reason, as
    `parse_stream` reports them (the live framer resolves a garbled frame in steps)."""
    first: Any = None
    buf = bytearray()
    end: float | None = None
    for ev in events:
        if ev.error is not None:
            if (
                first is not None
                and first.offset + len(buf) == ev.offset
                and len(buf) + len(ev.adu) <= MAX_DISCARD_RUN
            ):
                buf += ev.adu
                end = ev.end
                continue
            if first is not None:
                yield replace(first, adu=bytes(buf), end=end)
            first, buf, end = ev, bytearray(ev.adu), ev.end
            continue
        if first is not None:
            yield replace(first, adu=bytes(buf), end=end)
            first = None
        yield ev
    if first is not None:
        yield replace(first, adu=bytes(buf), end=end)


def stream_frames(
    runs: Iterable[tuple[bytes, float]],
    role: str = "monitor",
    *,
    backend: str | None = None,
    **options: Any,
) -> Iterator[Any]:
    """Frames of a byte stream of any size, in bounded memory: the streaming form of
    `parse_stream`.

    ``runs``: ``(data, time)`` pairs in order, ``time`` (seconds, ascending) being
    when the last byte of ``data`` arrived; the bytes before it are spread back at
    the character time, as `parse_stream` does with ``chunks``.  ``options`` are the
    keywords of `Framer` (baudrate, parity, ..., strict, rules).  The frames are
    those a live `Framer` finds: lenient mode ends a frame left incomplete by a
    silence at ``flush_timeout``, where `parse_stream` keeps looking across any
    silence (and can, by a CRC that checks by chance, swallow seconds of a damaged
    capture into one frame).  Contiguous discarded bytes are reported as one run
    (with the reason of its first byte, as `parse_stream` does), in pieces of at
    most `MAX_DISCARD_RUN` bytes.
    ``backend``: "c" or "python" (None: the active one).  A file of bytes without
    times (a raw dump) streams with the time 0 for every block; then, as for
    `parse_stream` without times, prediction and CRC alone split the stream::

        with open("dump.bin", "rb") as f:
            blocks = ((b, 0.0) for b in iter(lambda: f.read(1 << 16), b""))
            for frame in stream_frames(blocks, baudrate=9600):
                ...
    """
    return _join_discards(_framer_events(runs, role, backend, options))


def _framer_events(
    runs: Iterable[tuple[bytes, float]], role: str, backend: str | None, options: dict[str, Any]
) -> Iterator[Any]:
    framer = _backend_named(backend).Framer(role, **options)
    char = framer.options.bits / framer.options.baudrate
    timer = framer.timer
    receive = framer.receive_data
    handle = framer.handle_timer
    next_event = framer.next_event
    now = None
    for data, at in runs:
        # as a live framer: the timers due before the run's first byte fire first
        due = timer()
        if due is not None and due <= at - (len(data) - 1) * char:
            handle(due)
        receive(data, at)
        now = at
        while (ev := next_event()) is not None:
            yield ev
    if now is None:
        return
    for _ in range(16):  # resolve what is buffered: the silence after the last byte
        due = timer()
        if due is None:
            break
        handle(max(due, now))
        now = max(due, now)
        while (ev := next_event()) is not None:
            yield ev


def capture_frames(
    reader: CaptureReader | str, role: str = "monitor", **options: Any
) -> Iterator[Any]:
    """The frames of a capture file (path or open `CaptureReader`), streamed: memory
    stays bounded whatever the file's size.

    ``options``: `Framer` keywords (the byte format defaults to the capture's).
    A path is opened and closed here; pass a reader to read ``truncated`` after.
    """
    own = isinstance(reader, str)
    rd = CaptureReader(reader) if isinstance(reader, str) else reader
    try:
        kwargs = _format(rd.header)
        kwargs.update(options)
        char = rd.header.char_ns
        runs = ((seg, (rx0 + (len(seg) - 1) * char) / 1e9) for seg, rx0, _ in rd.segments())
        yield from stream_frames(runs, role, **kwargs)
    finally:
        if own:
            rd.close()


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
