"""The bridge's durable outbox: a bounded on-disk log between the poller and the broker.

Updates are appended (`append`), made durable in batches (`flush`, one fdatasync per
batch, when `flush_due` says so), read back from disk in sequence order (`pending`)
for publishing and released once delivered (`ack`).  The log is a directory of
segment files of checksummed records (format: _format.py); only per-segment
metadata and a sparse index (one entry per 64 KiB) are kept in memory, so memory stays
bounded whatever the backlog.

Guarantees:

* Sequence numbers are strictly increasing and never reused, even after SIGKILL or a
  power cut (a block of numbers is reserved in the cursor file before it is used).
* After `flush()` returns, every record appended before it survives a crash.  A crash
  loses at most the records appended since the last flush (one fsync batch).
* `pending()` returns only records that are durable (flushed), each with a verified
  checksum, so a published record never disappears or changes under its number.
* Recovery after a crash scans every segment, verifies each record's checksum, skips
  bad regions (counted in `corrupt`/`corrupt_bytes`) and truncates a torn tail.
* Disk budget (`OutboxLimits.max_bytes`): "drop-oldest" deletes the oldest segment(s)
  to make room, counting their unacked records in `dropped`; "refuse" raises
  `OutboxFull` and keeps everything already accepted.
* A full disk (ENOSPC) raises `OutboxError` saying so; records already accepted are
  kept (in memory until they can be written) and new ones are refused meanwhile.
* A record that can never be delivered (its topic no broker accepts) is moved aside
  by its reader (`quarantine`: copied to ``quarantine.jsonl``, see
  _quarantine.py) and then acked like a delivered one: it never blocks the
  records behind it, and its copy is durable before the ack cursor passes it.
"""

from __future__ import annotations

import bisect
import math
import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType

from pyrtu.outbox import _format as fmt
from pyrtu.outbox._format import Item
from pyrtu.outbox._parts import (
    RESERVE,
    WRITE_CHUNK,
    OutboxError,
    OutboxFull,
    OutboxLimits,
    Segment,
    active_reader,
    check_int,
    error,
    io_error,
    lock_directory,
    recover_segment,
)
from pyrtu.outbox._quarantine import Quarantine
from pyrtu.outbox._sync import Flushing

__all__ = ["Outbox", "OutboxError", "OutboxFull", "OutboxLimits"]


class Outbox(Flushing):
    """A durable, bounded, on-disk queue of records with sequence numbers (see module doc).

    Not thread-safe: one driver calls it.  Time is an input (`now` in seconds, any
    monotonic clock); the outbox never sleeps and never waits on the broker.
    """

    def __init__(
        self, directory: str | os.PathLike[str], limits: OutboxLimits | None = None
    ) -> None:
        if not isinstance(directory, (str, os.PathLike)):
            raise TypeError(f"directory must be a path, not {type(directory).__name__}")
        if limits is None:
            limits = OutboxLimits()
        elif not isinstance(limits, OutboxLimits):
            raise TypeError(f"limits must be an OutboxLimits, not {type(limits).__name__}")
        self.directory = Path(directory)
        self.limits = limits
        self._closed = True
        self._segs: list[Segment] = []
        self._firsts: list[int] = []
        self._active: Segment | None = None
        self._fd = -1  # the active segment, open for writing
        self._written = 0  # bytes of the active segment written to the file
        self._buf = bytearray()  # bytes of the active segment after _written
        self._unsynced: list[tuple[Segment, int]] = []  # sealed, written, not fsynced yet
        self._read_cache: tuple[Segment, int] | None = None
        self._dir_dirty = False
        self._state_lock = threading.Lock()
        self._write_failed = False
        self._next_seq = 1
        self._durable_seq = 0
        self._acked = 0
        self._dropped = 0
        self._reserved = 0
        self._gen = 0
        self._saved: tuple[int, int, int] = (0, 0, 0)  # acked, reserved, dropped on disk
        self._unflushed = 0
        self._unflushed_since: float | None = None
        self._dirty_since: float | None = None
        self._bytes_used = 0
        #: policy "refuse", once full: the bytes used then; every record is refused
        #: until acknowledged records free a segment (no flapping between a small
        #: record that fits and the next that does not)
        self._full_at: int | None = None
        self._total = 0
        self._hint: tuple[int, Segment, int] | None = None  # (seq, segment, offset)
        self._oldest: tuple[int, float] | None = None  # (acked, oldest_time) cache
        #: (first, last): durable records after every readable one, none of which can
        #: be read (damaged on disk since written): the ack reaching first - 1 passes them
        self._unreadable: tuple[int, int] | None = None
        self.appended = 0  # records appended since this Outbox was opened
        self.corrupt = 0  # bad regions (torn tail, bad checksum) found and skipped
        self.corrupt_bytes = 0
        self._dir_fd, self._lock_fd = lock_directory(self.directory)
        self._quarantine = Quarantine(self.directory, self._dir_fd)
        #: the file records are set aside in (made by the first `quarantine`)
        self.quarantine_path: Path = self._quarantine.path
        self._closed = False
        try:
            self._recover()
        except BaseException:
            self._release()
            raise

    # -- recovery ------------------------------------------------------------

    def _recover(self) -> None:
        state_path = self.directory / "cursor"
        try:
            self._state_fd = os.open(state_path, os.O_RDWR | os.O_CREAT, 0o644)
            data = os.pread(self._state_fd, fmt.STATE_SIZE, 0)
        except OSError as exc:
            raise self._io_error("reading", state_path.name, exc) from exc
        self._check_versions(data)
        state = fmt.decode_state(data)
        if state is None:
            if data.strip(b"\0"):
                self.corrupt += 1  # unreadable cursor: everything on disk is pending again
                self.corrupt_bytes += len(data)
            state = fmt.CursorState(0, 0, 0, 0)
        self._gen, self._acked, self._reserved, self._dropped = state
        self._saved = (self._acked, self._reserved, self._dropped)
        last = 0
        for name in sorted(os.listdir(self.directory)):
            m = fmt.SEGMENT_NAME.match(name)
            if m:
                seg = self._recover_segment(self.directory / name, int(m.group(1)), last)
                if seg is not None:
                    last = seg.last
        self._next_seq = max(last, self._acked) + 1
        self._next_seq = max(self._next_seq, self._reserved)
        self._durable_seq = self._next_seq - 1
        tail = self._segs[-1] if self._segs else None
        if tail is not None and tail.last + 1 == self._next_seq:
            self._open_active(tail)
        self._dir_dirty = True
        self._sync_dir()
        self._save_state(reserved=self._next_seq + RESERVE)  # ahead of the first append

    def _check_versions(self, cursor: bytes) -> None:
        """Refuse an outbox of another format version (a newer pyrtu's) before anything
        in it is read as corrupt, deleted or written over."""
        found = [("cursor", fmt.cursor_version(cursor))]
        for name in sorted(os.listdir(self.directory)):
            if fmt.SEGMENT_NAME.match(name):
                try:
                    with open(self.directory / name, "rb") as f:
                        head = f.read(fmt.SEG_HEAD.size)
                except OSError as exc:
                    raise self._io_error("reading", name, exc) from exc
                found.append((name, fmt.segment_version(head)))
        for name, version in found:
            if version != fmt.FORMAT_VERSION:
                raise OutboxError(
                    f"outbox {self.directory}: {name} is in outbox format version {version}, "
                    f"and this pyrtu reads version {fmt.FORMAT_VERSION} only (was it written "
                    "by a newer pyrtu?): upgrade pyrtu, or move the directory away"
                )

    def _recover_segment(self, path: Path, first: int, last: int) -> Segment | None:
        try:
            seg, bad, bad_bytes = recover_segment(path, first, last, self._acked)
        except OutboxError:
            raise
        except OSError as exc:
            raise self._io_error("recovering", path.name, exc) from exc
        self.corrupt += bad
        self.corrupt_bytes += bad_bytes
        if seg is not None:
            self._add_segment(seg)
        return seg

    def _add_segment(self, seg: Segment) -> None:
        self._segs.append(seg)
        self._firsts.append(seg.first)
        self._bytes_used += seg.size
        self._total += seg.count

    def _open_active(self, seg: Segment) -> None:
        try:
            self._fd = os.open(seg.path, os.O_RDWR)
        except OSError as exc:
            raise self._io_error("opening", seg.path.name, exc) from exc
        self._active = seg
        self._written = seg.size

    # -- appending -----------------------------------------------------------

    def append(self, record: bytes | bytearray | memoryview, now: float) -> int:
        """Append one record; returns its sequence number.

        The record is durable once the next `flush()` returns.  Budget exhausted:
        "drop-oldest" drops the oldest segments (their unacked records counted in
        `dropped`); "refuse" raises `OutboxFull`.  A disk error (ENOSPC) raises
        `OutboxError`; in both cases the record is not accepted and nothing accepted
        before is lost.
        """
        if not isinstance(record, bytes):
            if not isinstance(record, (bytearray, memoryview)):
                raise TypeError(f"record must be bytes, not {type(record).__name__}")
            record = bytes(record)  # (a memoryview's len() counts items, not bytes)
        if isinstance(now, bool) or not isinstance(now, (int, float)):
            raise TypeError(f"now must be a number of seconds, not {type(now).__name__}")
        if not math.isfinite(now):
            raise ValueError(f"now must be a finite number of seconds, got {now!r}")
        if self._closed:
            raise ValueError("append on a closed Outbox")
        n = len(record)
        limits = self.limits
        if n > limits.max_record:
            raise ValueError(
                f"record is {n} bytes; a segment of segment_bytes={limits.segment_bytes} "
                f"holds records of at most {limits.max_record} bytes"
            )
        size = fmt.REC_HEAD.size + n
        active = self._active
        rotate = active is None or active.size + size > limits.segment_bytes
        need = size + fmt.SEG_HEAD.size if rotate else size  # a new segment has a header
        still_full = self._full_at is not None and self._bytes_used >= self._full_at
        if still_full or self._bytes_used + need > limits.max_bytes:
            if limits.policy == "refuse":
                if self._full_at is None:
                    self._full_at = self._bytes_used
                raise error(
                    f"outbox {self.directory} is full: {self._bytes_used} bytes on disk, "
                    f"max_bytes={limits.max_bytes}; the record of {n} bytes is refused "
                    f"(policy 'refuse'); {self.depth} unacked records are kept",
                    cls=OutboxFull,
                )
            self._make_room(need)
        if self._write_failed:  # the disk was full: accept nothing until a write works
            self._write_out()
        seq = self._next_seq
        if seq >= self._reserved:
            self._save_state(reserved=seq + RESERVE)
        if rotate or active is None:
            active = self._rotate(seq)
        elif len(self._buf) >= WRITE_CHUNK:
            self._write_out()
        off = active.size
        self._buf += fmt.encode_record(seq, now, record)
        active.note(seq, off, off + size)
        self._bytes_used += size
        self._total += 1
        self._next_seq = seq + 1
        self.appended += 1
        self._unflushed += 1
        if self._unflushed_since is None:
            self._unflushed_since = now
        return seq

    def _rotate(self, seq: int) -> Segment:
        """Seal the active segment (written, fsynced at the next flush); start a new one."""
        old = self._active
        if old is not None:
            self._write_out()
            self._unsynced.append((old, self._fd))
            if old.last <= self._acked:
                self._forget(old)
            self._fd, self._active = -1, None
        seg = Segment(self.directory / fmt.segment_name(seq), seq)
        try:
            fd = os.open(seg.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise self._io_error("creating", seg.path.name, exc) from exc
        self._fd, self._active, self._written = fd, seg, 0
        self._buf = bytearray(fmt.segment_header(seq))
        self._add_segment(seg)
        self._dir_dirty = True
        return seg

    def _make_room(self, size: int) -> None:
        """Drop the oldest segments; the count is on disk before they go (a crash must
        not hide a drop)."""
        free, victims = self._bytes_used + size - self.limits.max_bytes, []
        for seg in self._segs:
            if free <= 0 or seg is self._active:
                break
            victims.append(seg)
            free -= seg.size
            self._dropped += seg.count - seg.acked_in(self._acked)
            self._acked = max(self._acked, seg.last)
        if victims:  # the cursor first: a crash between must not bring them back unseen
            self._save_state()
        for seg in victims:
            self._forget(seg)

    def _forget(self, seg: Segment) -> None:
        """Delete a sealed segment that is acked or dropped; close its file descriptors."""
        if self._read_cache is not None and self._read_cache[0] is seg:
            os.close(self._read_cache[1])
            self._read_cache = None
        for entry in self._unsynced:
            if entry[0] is seg:
                self._unsynced.remove(entry)
                os.close(entry[1])
                break
        i = bisect.bisect_left(self._firsts, seg.first)
        del self._segs[i], self._firsts[i]
        self._bytes_used -= seg.size
        if self._full_at is not None and self._bytes_used < self._full_at:
            self._full_at = None  # room again: records are taken
        self._total -= seg.count
        self._oldest = None
        if self._hint is not None and self._hint[1] is seg:
            self._hint = None
        try:
            os.unlink(seg.path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise self._io_error("deleting", seg.path.name, exc) from exc

    def _write_out(self) -> None:
        """Write the buffered bytes of the active segment (no fsync)."""
        buf = self._buf
        if not buf:
            self._write_failed = False
            return
        done = 0
        view = memoryview(buf)
        try:
            while done < len(view):
                done += os.pwrite(self._fd, view[done:], self._written + done)
        except OSError as exc:
            assert self._active is not None
            self._write_failed = True
            raise self._io_error("writing", self._active.path.name, exc) from exc
        else:
            self._write_failed = False
        finally:
            view.release()
            if done:
                del buf[:done]
                self._written += done

    def _io_error(self, action: str, name: str, exc: OSError) -> OutboxError:
        return io_error(self.directory, action, name, exc)

    # -- reading and acknowledging ---------------------------------------------

    def _reader(self, seg: Segment) -> Callable[[int, int], bytes]:
        """read(off, n) over a segment as appended, unwritten bytes included."""
        if seg is self._active:
            return active_reader(self._fd, self._written, self._buf)
        if self._read_cache is None or self._read_cache[0] is not seg:
            if self._read_cache is not None:
                os.close(self._read_cache[1])
                self._read_cache = None
            try:
                fd = os.open(seg.path, os.O_RDONLY)
            except OSError as exc:
                raise self._io_error("opening", seg.path.name, exc) from exc
            self._read_cache = (seg, fd)
        rfd = self._read_cache[1]
        return lambda off, n: os.pread(rfd, n, off)

    def _records(self, start: int, stop: int, chunk: int) -> Iterator[tuple[Segment, Item]]:
        """The valid records with start <= seq <= stop, in order, read from disk."""
        i = max(0, bisect.bisect_right(self._firsts, start) - 1)
        for seg in self._segs[i:]:
            if seg.last < start or seg.count == 0:
                continue
            if seg.first > stop:
                return
            off = seg.offset_for(start)
            hint = self._hint
            if hint is not None and hint[1] is seg and off <= hint[2] and hint[0] <= start:
                off = hint[2]
            try:
                for item in fmt.scan(
                    self._reader(seg),
                    off,
                    seg.size,
                    last_seq=seg.first - 1,
                    max_seq=seg.last,
                    chunk=chunk,
                ):
                    if item.seq < 0:
                        if item.off not in seg.bad:  # gone bad since recovery: count it once
                            seg.bad.add(item.off)
                            self.corrupt += 1
                            self.corrupt_bytes += item.end - item.off
                        continue
                    if item.seq > stop:
                        return
                    if item.seq >= start:
                        yield seg, item
            except OSError as exc:
                raise self._io_error("reading", seg.path.name, exc) from exc

    def pending(self, limit: int, after: int | None = None) -> list[tuple[int, bytes]]:
        """Up to `limit` unacked, durable records (seq, record) in sequence order.

        Starts after `after` (a publish cursor that runs ahead of the acks) or after
        the ack cursor, whichever is higher.  Records are read from disk and their
        checksums verified; only records made durable by flush() are returned.
        """
        check_int("limit", limit, 0)
        if after is not None:
            check_int("after", after, 0)
        if self._closed:
            raise ValueError("pending on a closed Outbox")
        start = max(self._acked, after or 0) + 1
        out: list[tuple[int, bytes]] = []
        if limit == 0 or start > self._durable_seq:
            return out
        chunk = min(1 << 20, max(4096, limit * 256))
        last = start - 1
        for seg, item in self._records(start, self._durable_seq, chunk):
            assert item.payload is not None
            out.append((item.seq, item.payload))
            self._hint = (item.seq + 1, seg, item.end)
            last = item.seq
            if len(out) >= limit:
                break
        else:  # every durable record read: those after the last one found cannot be
            self._pass_unreadable(last + 1, self._durable_seq)
        return out

    def _pass_unreadable(self, first: int, last: int) -> None:
        """Durable records first..last can never be delivered: none of them reads (each
        damaged on disk since it was written, counted in `corrupt`, or a number a
        restart's scan found missing).  The acks pass them, now if every record before
        them is acked, else with the ack that reaches first - 1: `depth` and a drain
        wait for no record that can never be delivered."""
        if first > last:
            return
        if self._acked >= first - 1:
            self.ack(last)
        else:
            self._unreadable = (first, last)

    def ack(self, seq: int) -> None:
        """Every record with a sequence number <= seq is delivered.

        Acks form a contiguous prefix: with QoS 1 acknowledgements arriving out of
        order, the caller acks the highest sequence number below which every record
        is delivered.  The cursor is persisted with the next flush(); fully acked
        segments are deleted at once.  Acking a lower number than before is a no-op.
        """
        check_int("seq", seq, 0)
        if seq >= self._next_seq:
            raise ValueError(f"seq must be in 0..{self._next_seq - 1} (appended so far), got {seq}")
        if self._closed:
            raise ValueError("ack on a closed Outbox")
        unreadable = self._unreadable
        if unreadable is not None and seq >= unreadable[0] - 1:
            seq = max(seq, unreadable[1])  # and the unreadable records after it
            self._unreadable = None
        if seq <= self._acked:
            return
        self._quarantine.sync()  # what was set aside is on disk before the cursor passes it
        self._acked = seq
        self._oldest = None
        while self._segs and self._segs[0] is not self._active and self._segs[0].last <= seq:
            self._forget(self._segs[0])

    def quarantine(self, seq: int, record: bytes, reason: str) -> None:
        """Set aside a record that can never be delivered (``reason`` says why):
        copied to the directory's ``quarantine.jsonl``; the caller then acks past it
        as if delivered.  Counted in `quarantined`; OutboxError on a disk error."""
        check_int("seq", seq, 1)
        if self._closed:
            raise ValueError("quarantine on a closed Outbox")
        self._quarantine.add(seq, bytes(record), reason)

    @property
    def quarantined(self) -> int:
        """Records set aside (`quarantine`) since this Outbox was opened."""
        return self._quarantine.count

    # -- statistics ------------------------------------------------------------

    @property
    def depth(self) -> int:
        """Records appended and not yet acked (nor dropped)."""
        if not self._segs:
            return 0
        return self._total - self._segs[0].acked_in(self._acked)

    @property
    def bytes_used(self) -> int:
        """Bytes of the segment files (including records not yet written)."""
        return self._bytes_used

    @property
    def oldest_time(self) -> float | None:
        """The `now` given at append of the oldest unacked record (None if none)."""
        if self._oldest is not None and self._oldest[0] == self._acked:
            return self._oldest[1]
        if self.depth == 0:
            return None
        for _seg, item in self._records(self._acked + 1, self._next_seq - 1, 4096):
            self._oldest = (self._acked, float(item.time))
            return float(item.time)
        return None

    @property
    def dropped(self) -> int:
        """Unacked records dropped by the "drop-oldest" policy since the directory was made."""
        return self._dropped

    @property
    def next_seq(self) -> int:
        """The sequence number the next append() returns."""
        return self._next_seq

    @property
    def acked(self) -> int:
        """The ack cursor: every record with a sequence number <= acked is done."""
        return self._acked

    @property
    def durable_seq(self) -> int:
        """Every record with a sequence number <= durable_seq has been flushed."""
        return self._durable_seq

    def stats(self) -> dict[str, int | float | None]:
        return {
            "depth": self.depth,
            "bytes_used": self._bytes_used,
            "max_bytes": self.limits.max_bytes,
            "oldest_time": self.oldest_time,
            "dropped": self._dropped,
            "appended": self.appended,
            "next_seq": self._next_seq,
            "acked": self._acked,
            "durable_seq": self._durable_seq,
            "segments": len(self._segs),
            "corrupt": self.corrupt,
            "corrupt_bytes": self.corrupt_bytes,
            "quarantined": self.quarantined,
        }

    # -- closing ---------------------------------------------------------------

    def close(self) -> None:
        """Flush, persist the cursor and release the lock (idempotent).

        If the final flush fails (disk full) the error is raised after the lock is
        released; records not flushed are then lost, as after a crash.
        """
        if self._closed:
            return
        try:
            self._quarantine.sync()  # before the cursor is saved
            self.flush()
            self._save_state(reserved=self._next_seq)  # clean: no gap in the numbers
        finally:
            self._release()

    def _release(self) -> None:
        try:
            self._quarantine.close()
        except OutboxError:
            pass  # close() synced it; after a failure the lines stay as after a crash
        fds = [fd for _seg, fd in self._unsynced]
        fds += [self._fd, self._dir_fd, getattr(self, "_state_fd", -1)]
        if self._read_cache is not None:
            fds.append(self._read_cache[1])
        self._unsynced, self._read_cache, self._fd, self._active = [], None, -1, None
        for fd in fds:
            if fd >= 0:
                os.close(fd)
        self._closed = True
        os.close(self._lock_fd)  # releases the flock

    def __enter__(self) -> Outbox:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"depth={self.depth} next_seq={self._next_seq}"
        return f"<Outbox {str(self.directory)!r} {state}>"
