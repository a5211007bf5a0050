"""Every sync the outbox's durability rests on, seen as system calls by strace.

A child opens an outbox with small segments, appends enough records for several
segments (sealed ones and the active one), flushes, acknowledges part of them and
flushes again, writing a marker to its stdout between the phases.  strace (``-y``:
each file descriptor with its path) records the syscalls; each test reads, between
two markers, that a file was made durable after its last write:

* the active segment and every sealed segment written since the last flush:
  ``fdatasync`` of each, after its last ``pwrite64``, within the flush;
* the directory: ``fsync`` after the segment files were created (a new file's
  name is durable only with its directory), within the flush; and when the outbox
  opens, after the cursor file was created;
* the cursor: ``fdatasync`` after its ``pwrite64``, within the flush that saves it.

A segment deleted by an acknowledgement needs no directory sync: the cursor saved
by the next flush says its records are done, so one that comes back after a power
cut is read as acknowledged (test_bridge_outbox.py checks that recovery).

strace is installed by the Makefile (APT_PACKAGES) and .ci/run; without it the
tests skip, which CI turns into a failure (tests/conftest.py).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

CHILD = textwrap.dedent(
    """
    import os, sys
    from pyrtu.outbox.outbox import Outbox, OutboxLimits

    def mark(name):
        os.write(1, b"MARK:" + name.encode() + b"\\n")

    limits = OutboxLimits(max_bytes=1 << 20, segment_bytes=4096,
                          fsync_records=10**6, fsync_interval=3600.0)
    mark("OPEN")
    ob = Outbox(sys.argv[1], limits)
    mark("APPEND")
    for i in range(200):  # 128 bytes a record: 32 a segment, 7 segments
        ob.append(bytes([i]) * 100, float(i))
    mark("FLUSH")
    ob.flush()
    mark("FLUSHED")
    ob.ack(150)  # deletes the segments every record of which is acknowledged
    mark("ACKED")
    ob.flush()
    mark("ACK-FLUSHED")
    ob.close()
    mark("CLOSED")
    """
)

SYSCALL = re.compile(r"^(?:\[pid\s+\d+\]\s+|\d+\s+)?(\w+)\((.*)$")
FD_PATH = re.compile(r"^-?\d+<([^>]*)>")
OPENED = re.compile(r'^\w+<[^>]*>, "([^"]+)", ([A-Z_|]+).*= \d+<')
UNLINKED = re.compile(r'^(?:\w+<[^>]*>, )?"([^"]+)"')
MARK = re.compile(r'"MARK:([A-Z-]+)\\n"')


@dataclass(frozen=True)
class Call:
    name: str
    path: str  # the file descriptor's path, or the path opened
    flags: str = ""


@dataclass
class Trace:
    directory: Path
    calls: list[Call]
    marks: dict[str, int]  # marker -> index in calls

    def between(self, start: str, end: str) -> list[tuple[int, Call]]:
        return [(i, c) for i, c in enumerate(self.calls) if self.marks[start] < i < self.marks[end]]

    def segments(self) -> list[str]:
        """The segment files created, in order."""
        return [
            c.path
            for c in self.calls
            if c.name == "openat" and "O_CREAT" in c.flags and c.path.endswith(".seg")
        ]

    def last(self, name: str, path: str, before: int) -> int:
        """The index of the last ``name`` call on ``path`` before ``before`` (-1: none)."""
        return max(
            (i for i, c in enumerate(self.calls[:before]) if c.name == name and c.path == path),
            default=-1,
        )


def parse(text: str, directory: Path) -> Trace:
    calls: list[Call] = []
    marks: dict[str, int] = {}
    for line in text.splitlines():
        m = SYSCALL.match(line)
        if m is None:
            continue
        name, rest = m.groups()
        if name == "write" and (mk := MARK.search(rest)):
            marks[mk.group(1)] = len(calls)
            calls.append(Call("mark", mk.group(1)))
        elif name == "openat" and (op := OPENED.match(rest)):
            calls.append(Call(name, os.path.realpath(op.group(1)), op.group(2)))
        elif name in ("unlink", "unlinkat") and (un := UNLINKED.match(rest)):
            calls.append(Call(name, os.path.realpath(un.group(1))))
        elif (fd := FD_PATH.match(rest)) is not None:
            calls.append(Call(name, fd.group(1)))
    return Trace(directory, calls, marks)


@pytest.fixture(scope="module")
def trace(tmp_path_factory: pytest.TempPathFactory) -> Trace:
    strace = shutil.which("strace")
    if strace is None:
        pytest.skip("strace is not installed (apt-get install strace; make system-packages)")
    tmp = tmp_path_factory.mktemp("durability")
    directory = (tmp / "ob").resolve()
    log = tmp / "trace"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    r = subprocess.run(
        [strace, "-f", "-y", "-s", "64", "-e", "signal=none",
         "-e", "trace=openat,write,pwrite64,fdatasync,fsync,unlink,unlinkat",
         "-o", str(log), sys.executable, "-c", CHILD, str(directory)],
        capture_output=True, env=env, timeout=120,
    )  # fmt: skip
    if r.returncode != 0 and b"ptrace" in r.stderr:
        pytest.skip(f"strace cannot trace here: {r.stderr.decode().strip()}")
    assert r.returncode == 0, r.stderr.decode()
    marks = [ln for ln in r.stdout.decode().splitlines()]
    assert marks == [
        f"MARK:{m}"
        for m in ("OPEN", "APPEND", "FLUSH", "FLUSHED", "ACKED", "ACK-FLUSHED", "CLOSED")
    ]
    t = parse(log.read_text(), directory)
    assert list(t.marks) == [
        "OPEN",
        "APPEND",
        "FLUSH",
        "FLUSHED",
        "ACKED",
        "ACK-FLUSHED",
        "CLOSED",
    ], t.marks
    assert len(t.segments()) >= 5, t.segments()  # several sealed segments and the active one
    return t


def synced_after_last_write(
    t: Trace, path: str, start: str, end: str, sync: str = "fdatasync"
) -> None:
    window = t.between(start, end)
    syncs = [i for i, c in window if c.name == sync and c.path == path]
    assert syncs, f"no {sync} of {path} between {start} and {end}"
    last_write = t.last("pwrite64", path, t.marks[end])
    assert last_write >= 0, f"{path} was never written"
    assert max(syncs) > last_write, f"{path}: written after its last {sync}"


def test_the_flush_fdatasyncs_the_active_segment(trace: Trace) -> None:
    active = trace.segments()[-1]
    synced_after_last_write(trace, active, "FLUSH", "FLUSHED")


def test_the_flush_fdatasyncs_every_sealed_segment(trace: Trace) -> None:
    for sealed in trace.segments()[:-1]:
        synced_after_last_write(trace, sealed, "FLUSH", "FLUSHED")


def test_the_directory_is_fsynced_after_files_are_created(trace: Trace) -> None:
    directory = str(trace.directory)
    created = [i for i, c in enumerate(trace.calls) if c.name == "openat" and "O_CREAT" in c.flags]
    in_flush = [
        i for i, c in trace.between("FLUSH", "FLUSHED") if c.name == "fsync" and c.path == directory
    ]
    last_segment = max(i for i in created if trace.calls[i].path.endswith(".seg"))
    assert in_flush and max(in_flush) > last_segment, "the segments' names were not made durable"
    # opening: the cursor file (and the lock) created, the directory fsynced before the first append
    cursor = str(trace.directory / "cursor")
    made = [i for i in created if trace.calls[i].path == cursor]
    assert made and made[0] < trace.marks["APPEND"]
    at_open = [
        i for i, c in trace.between("OPEN", "APPEND") if c.name == "fsync" and c.path == directory
    ]
    assert at_open and max(at_open) > made[0]


def test_the_cursor_is_fdatasynced_when_saved(trace: Trace) -> None:
    cursor = str(trace.directory / "cursor")
    # the acknowledgement's flush writes the cursor and makes it durable
    assert any(
        c.name == "pwrite64" and c.path == cursor for _, c in trace.between("ACKED", "ACK-FLUSHED")
    )
    synced_after_last_write(trace, cursor, "ACKED", "ACK-FLUSHED")
    # the block of numbers reserved when the outbox opens, too
    synced_after_last_write(trace, cursor, "OPEN", "APPEND")
    # the acknowledged segments went at once (before the flush)
    gone = [
        c.path for _, c in trace.between("FLUSHED", "ACKED") if c.name in ("unlink", "unlinkat")
    ]
    assert len(gone) >= 3 and set(gone) <= set(trace.segments())
