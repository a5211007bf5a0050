"""The outbox's building blocks: its errors, its limits and a segment's in-memory index.

See outbox.py for the Outbox itself and _format.py for the bytes on disk.
"""

from __future__ import annotations

import bisect
import errno
import fcntl
import math
import os
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pyrtu.outbox import _format as fmt

INDEX_STRIDE = 1 << 16  # bytes between sparse index entries
WRITE_CHUNK = 1 << 18  # unwritten bytes kept in memory before they are written
RESERVE = 1 << 16  # sequence numbers reserved in the cursor file at a time
_POLICIES = ("drop-oldest", "refuse")


class OutboxError(OSError):
    """The outbox cannot do its work: disk full or failing, directory unusable or locked."""


class OutboxFull(OutboxError):
    """The disk budget is exhausted and the policy is "refuse"; nothing was lost."""


def error(
    message: str, exc: OSError | None = None, cls: type[OutboxError] = OutboxError
) -> OutboxError:
    err = cls(message)
    if exc is not None:
        err.errno = exc.errno
    return err


def io_error(directory: Path, action: str, name: str, exc: OSError) -> OutboxError:
    """An OutboxError naming the directory, the file and what failed."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return error(
            f"outbox {directory}: the disk is full ({exc.strerror}) {action} {name}; "
            "records already accepted are kept and new ones are refused until space is freed",
            exc,
        )
    return error(f"outbox {directory}: {action} {name}: {exc.strerror or exc}", exc)


def lock_directory(directory: Path) -> tuple[int, int]:
    """Create the directory and lock it for this process: (its fd, the lock file's fd)."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        dir_fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise io_error(directory, "opening", "the directory", exc) from exc
    try:
        lock_fd = os.open(directory / "lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        os.close(dir_fd)
        raise io_error(directory, "opening", "the lock file", exc) from exc
    try:
        fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(lock_fd)
        os.close(dir_fd)
        if exc.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
            raise io_error(directory, "locking", "the lock file", exc) from exc
        raise error(
            f"outbox directory {directory} is in use by another Outbox "
            f"(its lock file {directory / 'lock'} is held)",
            exc,
        ) from exc
    return dir_fd, lock_fd


def check_int(name: str, value: object, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, not {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")


@dataclass(frozen=True)
class OutboxLimits:
    """Disk budget, segment size, fsync batching and what to do when the budget is full."""

    max_bytes: int = 256 * 2**20
    segment_bytes: int = 8 * 2**20
    fsync_interval: float = 0.05
    fsync_records: int = 4096
    policy: Literal["drop-oldest", "refuse"] = "drop-oldest"

    def __post_init__(self) -> None:
        check_int("segment_bytes", self.segment_bytes, 1024)
        check_int("max_bytes", self.max_bytes, 2 * self.segment_bytes)
        check_int("fsync_records", self.fsync_records, 1)
        v = self.fsync_interval
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"fsync_interval must be a number of seconds, not {type(v).__name__}")
        if not 0.0 <= v < math.inf:
            raise ValueError(f"fsync_interval must be a finite number of seconds >= 0, got {v!r}")
        if not isinstance(self.policy, str):
            raise TypeError(f"policy must be a str, not {type(self.policy).__name__}")
        if self.policy not in _POLICIES:
            raise ValueError(f"policy must be 'drop-oldest' or 'refuse', got {self.policy!r}")

    @property
    def max_record(self) -> int:
        """The largest payload a segment can hold."""
        return self.segment_bytes - fmt.SEG_HEAD.size - fmt.REC_HEAD.size


class Segment:
    """What memory holds of one segment file: its range, size and a sparse index."""

    __slots__ = ("bad", "count", "first", "gaps", "idx_off", "idx_seq", "last", "path", "size")

    def __init__(self, path: Path, first: int) -> None:
        self.path = path
        self.first = first  # the sequence number it is named by
        self.last = first - 1  # the highest valid sequence number in it
        self.count = 0  # valid records
        self.size = fmt.SEG_HEAD.size  # bytes, including those not yet written
        self.idx_seq = array("q")  # sparse index: the record of idx_seq[i] is at idx_off[i]
        self.idx_off = array("q")
        self.bad: set[int] = set()  # offsets of bad regions already counted
        # sequence numbers missing between its valid records (records damaged on
        # disk, found by a restart's scan), as (first, last) ranges in order
        self.gaps: list[tuple[int, int]] = []

    def note(self, seq: int, off: int, end: int) -> None:
        """A valid record [off, end) with sequence number `seq` follows the others."""
        if off - (self.idx_off[-1] if self.idx_off else 0) >= INDEX_STRIDE:
            self.idx_seq.append(seq)
            self.idx_off.append(off)
        if seq > self.last + 1:
            self.gaps.append((self.last + 1, seq - 1))
        self.last = seq
        self.count += 1
        self.size = end

    def offset_for(self, seq: int) -> int:
        """An offset at or before the first record with a sequence number >= seq."""
        i = bisect.bisect_right(self.idx_seq, seq) - 1
        return self.idx_off[i] if i >= 0 else fmt.SEG_HEAD.size

    def acked_in(self, acked: int) -> int:
        """How many of its records have sequence numbers <= acked (the numbers of
        damaged records, `gaps`, not counted)."""
        if acked >= self.last:
            return self.count
        if acked < self.first:
            return 0
        missing = sum(min(hi, acked) - lo + 1 for lo, hi in self.gaps if lo <= acked)
        return acked - self.first + 1 - missing


def recover_segment(
    path: Path, first: int, last: int, acked: int
) -> tuple[Segment | None, int, int]:
    """Scan one segment file after a restart and repair it.

    Returns its index (None if it held nothing unacked and was deleted), the number
    of bad regions skipped and their bytes.  A torn tail is truncated and the file
    fsynced.  `last` is the highest sequence number of the segments before it.
    """
    bad = bad_bytes = 0
    fd = os.open(path, os.O_RDWR)
    try:
        size = os.fstat(fd).st_size
        head = os.pread(fd, fmt.SEG_HEAD.size, 0)
        if size >= fmt.SEG_HEAD.size and fmt.parse_segment_header(head) != first:
            raise error(
                f"outbox {path.parent}: {path.name} is not an outbox segment of this format "
                "(bad header); move it out of the directory"
            )
        seg = Segment(path, first)

        def read(off: int, n: int) -> bytes:
            return os.pread(fd, n, off)

        end = fmt.SEG_HEAD.size
        for item in fmt.scan(read, end, size, last_seq=max(last, first - 1)):
            if item.seq < 0:
                seg.bad.add(item.off)
                bad += 1
                bad_bytes += item.end - item.off
            else:
                seg.note(item.seq, item.off, item.end)
                end = item.end
        if seg.count == 0 or seg.last <= acked:
            os.close(fd)
            fd = -1
            os.unlink(path)
            return None, bad, bad_bytes
        if end < size:
            os.ftruncate(fd, end)
        os.fdatasync(fd)
    finally:
        if fd >= 0:
            os.close(fd)
    return seg, bad, bad_bytes


def active_reader(fd: int, written: int, buf: bytearray) -> Callable[[int, int], bytes]:
    """read(off, n) over the active segment: `written` bytes in the file, then `buf`."""

    def read(off: int, n: int) -> bytes:
        if off >= written:
            return bytes(buf[off - written : off - written + n])
        data = os.pread(fd, min(n, written - off), off)
        if off + n > written and len(data) == written - off:
            data += bytes(buf[: off + n - written])
        return data

    return read


__all__ = [
    "INDEX_STRIDE",
    "RESERVE",
    "WRITE_CHUNK",
    "OutboxError",
    "OutboxFull",
    "OutboxLimits",
    "Segment",
    "active_reader",
    "check_int",
    "error",
    "io_error",
    "lock_directory",
    "recover_segment",
]
