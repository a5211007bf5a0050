"""The bridge's durable outbox (pyrtu.bridge.outbox): a bounded, checksummed on-disk log.

Crashes are real (a child process SIGKILLed at random points), a full disk is a real
tiny tmpfs, the lock is held by another process.
"""

from __future__ import annotations

import errno
import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pyrtu.bridge import _outbox_format as fmt
from pyrtu.bridge.outbox import Outbox, OutboxError, OutboxFull, OutboxLimits

SMALL = OutboxLimits(max_bytes=1 << 20, segment_bytes=4096)


def payload(seq: int) -> bytes:
    """A record whose content is known from its sequence number (length 1..64)."""
    digest = hashlib.blake2b(str(seq).encode(), digest_size=32).digest()
    return (digest * 2)[: 1 + seq % 64]


def fill(ob: Outbox, n: int, t0: float = 0.0) -> list[int]:
    seqs = []
    for i in range(n):
        seqs.append(ob.append(payload(ob.next_seq), t0 + i))
    return seqs


def everything(ob: Outbox, after: int | None = None) -> list[tuple[int, bytes]]:
    out: list[tuple[int, bytes]] = []
    while True:
        batch = ob.pending(97, after=out[-1][0] if out else after)
        if not batch:
            return out
        out.extend(batch)


def segments(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.suffix == ".seg")


# -- round trip, restart, acks ------------------------------------------------


def test_round_trip_in_order_only_after_flush(tmp_path: Path) -> None:
    with Outbox(tmp_path / "ob", SMALL) as ob:
        assert ob.next_seq == 1 and ob.depth == 0 and ob.oldest_time is None
        seqs = fill(ob, 500, t0=100.0)
        assert seqs == list(range(1, 501))
        assert ob.depth == 500 and ob.appended == 500 and ob.oldest_time == 100.0
        assert ob.pending(10) == []  # nothing is durable yet: nothing to publish
        ob.flush()
        assert ob.durable_seq == 500
        assert ob.pending(3) == [(s, payload(s)) for s in (1, 2, 3)]
        assert ob.pending(2, after=498) == [(499, payload(499)), (500, payload(500))]
        assert ob.pending(5, after=500) == []
        assert everything(ob) == [(s, payload(s)) for s in seqs]
        assert len(segments(tmp_path / "ob")) >= 7  # 4 KiB segments: many rotations
        stats = ob.stats()
        assert stats["depth"] == 500 and stats["dropped"] == 0 and stats["corrupt"] == 0
        assert stats["bytes_used"] == sum(p.stat().st_size for p in segments(tmp_path / "ob"))


def test_restart_keeps_pending_and_continues_the_numbers(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    with Outbox(d, SMALL) as ob:
        fill(ob, 300, t0=5.0)
        ob.flush()
        ob.ack(120)
    with Outbox(d, SMALL) as ob:
        assert ob.acked == 120 and ob.depth == 180 and ob.next_seq == 301
        assert ob.oldest_time == 5.0 + 120
        assert everything(ob) == [(s, payload(s)) for s in range(121, 301)]
        assert ob.append(b"next", 1.0) == 301
    with Outbox(d, SMALL) as ob:  # close() flushed it
        assert ob.pending(1, after=300) == [(301, b"next")] and ob.next_seq == 302


def run_child(code: str, *args: str) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, env=env
    )


def test_ack_deletes_fully_acked_segments_and_persists_with_flush(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    ob = Outbox(d, SMALL)
    fill(ob, 400)
    ob.flush()
    before = segments(d)
    ob.ack(200)
    after = segments(d)
    assert len(after) < len(before)
    firsts = [int(p.stem) for p in after]
    assert firsts[0] <= 201 and (len(firsts) == 1 or firsts[1] > 201)
    assert ob.depth == 200 and ob.pending(1) == [(201, payload(201))]
    assert ob.bytes_used == sum(p.stat().st_size for p in after)
    ob.ack(150)  # lower than before: no-op
    assert ob.acked == 200
    assert not ob.flush_due(50.0) and ob.flush_at == 50.0 + SMALL.fsync_interval
    assert ob.flush_due(50.0 + SMALL.fsync_interval)
    ob.flush()
    assert ob.flush_at is None and not ob.flush_due(60.0)
    ob.ack(400)  # everything: sealed segments go, the active one stays until sealed
    assert ob.depth == 0 and ob.oldest_time is None and len(segments(d)) == 1
    ob.close()
    with Outbox(d, SMALL) as again:
        assert again.acked == 400 and again.depth == 0 and again.pending(10) == []
        assert segments(d) == [] and again.next_seq == 401


def test_flushed_acks_survive_sigkill(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    with Outbox(d, SMALL) as ob:
        fill(ob, 100)
    r = run_child(
        """
        import os, signal, sys
        from pyrtu.bridge.outbox import Outbox, OutboxLimits
        ob = Outbox(sys.argv[1], OutboxLimits(max_bytes=1 << 20, segment_bytes=4096))
        ob.ack(60)
        ob.flush()
        ob.ack(80)  # not flushed: the cursor on disk stays at 60
        os.kill(os.getpid(), signal.SIGKILL)
        """,
        str(d),
    )
    assert r.returncode == -signal.SIGKILL, r.stderr
    with Outbox(d, SMALL) as ob:
        assert ob.acked == 60
        got = [s for s, _ in everything(ob)]
        # acked records may be gone with their segments (they were delivered); all
        # the others are there
        assert got == list(range(got[0], 101)) and 61 <= got[0] <= 81
        assert ob.depth == len(got)


def test_flush_due_by_interval_and_by_count(tmp_path: Path) -> None:
    limits = OutboxLimits(
        max_bytes=1 << 20, segment_bytes=4096, fsync_interval=0.5, fsync_records=3
    )
    with Outbox(tmp_path / "ob", limits) as ob:
        assert ob.flush_at is None and not ob.flush_due(0.0)
        ob.append(b"a", 10.0)
        assert ob.flush_at == 10.5 and not ob.flush_due(10.49) and ob.flush_due(10.5)
        ob.append(b"b", 10.1)
        ob.append(b"c", 10.2)
        assert ob.flush_due(10.2) and ob.flush_at == 10.0
        ob.flush()
        assert ob.flush_at is None and not ob.flush_due(99.0)


# -- crash safety for real: SIGKILL at random points --------------------------

CHILD = textwrap.dedent(
    """
    import hashlib, os, random, sys
    from pyrtu.bridge.outbox import Outbox, OutboxLimits

    def payload(seq):
        digest = hashlib.blake2b(str(seq).encode(), digest_size=32).digest()
        return (digest * 2)[: 1 + seq % 64]

    rng = random.Random(int(sys.argv[2]))
    ob = Outbox(sys.argv[1], OutboxLimits(max_bytes=1 << 26, segment_bytes=8192))
    os.write(1, b"R %d\\n" % ob.next_seq)
    while True:
        for _ in range(rng.randint(1, 400)):
            seq = ob.append(payload(ob.next_seq), 0.0)
            os.write(1, b"A %d\\n" % seq)
        if rng.random() < 0.3 and ob.durable_seq > ob.acked:
            k = rng.randint(ob.acked + 1, ob.durable_seq)
            os.write(1, b"K %d\\n" % k)
            ob.ack(k)
        ob.flush()
        os.write(1, b"F %d %d\\n" % (ob.durable_seq, ob.acked))
    """
)


def _run_child_and_kill(d: Path, seed: int, rng: random.Random) -> list[list[int]]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(d), str(seed)], stdout=subprocess.PIPE, env=env
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()  # opened: now let it run a random while
    assert first.startswith(b"R "), first
    time.sleep(rng.uniform(0.0, 0.4))
    proc.send_signal(signal.SIGKILL)
    rest = proc.stdout.read()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    lines = (first + rest).split(b"\n")
    if not rest.endswith(b"\n"):
        lines = lines[:-1]  # a line cut by the kill
    return [[ord(ln[:1])] + [int(x) for x in ln[2:].split()] for ln in lines if ln]


def test_sigkill_at_random_points_loses_at_most_the_unflushed_batch(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=1 << 26, segment_bytes=8192)
    rng = random.Random(1919)
    handed: list[int] = []  # every sequence number any child was given, in order
    kept: set[int] = set()  # what the last reopen found, closed cleanly after
    acked_floor = 0
    for rnd in range(8):
        events = _run_child_and_kill(d, rnd, rng)
        mine: list[int] = []  # the numbers this child was given
        flushed, acked_at_flush, acks = 0, 0, [acked_floor]
        for ev in events:
            if ev[0] == ord("A"):
                mine.append(ev[1])
            elif ev[0] == ord("K"):
                acks.append(ev[1])
            elif ev[0] == ord("F"):
                flushed, acked_at_flush = ev[1], ev[2]
        handed += mine
        assert handed == sorted(set(handed)), "a sequence number was handed out twice"
        with Outbox(d, limits) as ob:
            assert ob.next_seq > handed[-1]  # never reused, even the unflushed ones
            assert max(acked_at_flush, acked_floor) <= ob.acked <= max(acks)
            got = everything(ob)
            for seq, rec in got:
                assert rec == payload(seq) and seq > ob.acked
            got_seqs = {s for s, _ in got}
            # records the child acked may be gone with their segments even if the kill
            # came before the ack cursor was flushed: they were delivered
            floor = max(ob.acked, *acks)
            must = [s for s in sorted(kept) + mine if floor < s and (s in kept or s <= flushed)]
            missing = [s for s in must if s not in got_seqs]
            assert missing == [], f"round {rnd}: flushed records lost: {missing[:10]}"
            # what is back beyond the last flush is a prefix of the unflushed batch
            tail = [s for s in mine if s > flushed]
            extra = sorted(s for s in got_seqs if s in tail)
            assert extra == tail[: len(extra)]
            assert got_seqs <= kept | set(mine)  # nothing that was never appended
            if rnd % 3 == 2 and got:
                ob.ack(got[len(got) // 2][0])  # a broker took some
            acked_floor = ob.acked
            kept = {s for s in got_seqs if s > ob.acked}
    assert len(handed) > 500  # the children did work between the kills


# -- torn and corrupt records -----------------------------------------------


def _one_segment(tmp_path: Path, n: int = 100) -> tuple[Path, Path]:
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, n)
    (seg,) = segments(d)
    return d, seg


def _offset_of(seg: Path, seq: int) -> int:
    data = seg.read_bytes()
    off = fmt.SEG_HEAD.size
    while off < len(data):
        _m, n, s, _t, _c = fmt.REC_HEAD.unpack_from(data, off)
        if s == seq:
            return off
        off += fmt.REC_HEAD.size + n
    raise AssertionError(seq)


def _flip(path: Path, off: int) -> None:
    with open(path, "r+b") as f:
        f.seek(off)
        b = f.read(1)
        f.seek(off)
        f.write(bytes([b[0] ^ 0x40]))


def test_torn_tail_is_truncated_counted_and_its_number_not_reused(tmp_path: Path) -> None:
    d, seg = _one_segment(tmp_path)
    size = seg.stat().st_size
    os.truncate(seg, size - 5)  # the last record is cut short
    with Outbox(d) as ob:
        assert ob.corrupt == 1 and ob.corrupt_bytes == size - 5 - _offset_of(seg, 99) - (
            fmt.REC_HEAD.size + len(payload(99))
        )
        got = everything(ob)
        assert [s for s, _ in got] == list(range(1, 100))
        assert all(rec == payload(s) for s, rec in got)
        assert seg.stat().st_size == _offset_of(seg, 99) + fmt.REC_HEAD.size + len(payload(99))
        assert ob.append(b"new", 0.0) == 101  # 100 was handed out once: never again


@pytest.mark.parametrize("where", ["payload", "length", "seq", "crc", "magic"])
def test_flipped_byte_skips_only_that_record(tmp_path: Path, where: str) -> None:
    d, seg = _one_segment(tmp_path)
    delta = {"magic": 1, "length": 5, "seq": 9, "crc": 25, "payload": 28}[where]
    _flip(seg, _offset_of(seg, 50) + delta)
    with Outbox(d) as ob:
        got = everything(ob)
        assert [s for s, _ in got] == [s for s in range(1, 101) if s != 50]
        assert all(rec == payload(s) for s, rec in got)
        assert ob.corrupt == 1 and ob.corrupt_bytes > 0 and ob.depth == 99
        assert ob.next_seq == 101


def test_corruption_while_open_is_skipped_and_counted_once(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    with Outbox(d, OutboxLimits(max_bytes=1 << 22, segment_bytes=1 << 20)) as ob:
        fill(ob, 100)
        ob.flush()
        (seg,) = segments(d)
        _flip(seg, _offset_of(seg, 7) + 30)
        for _ in range(2):
            got = everything(ob)
            assert [s for s, _ in got] == [s for s in range(1, 101) if s != 7]
        assert ob.corrupt == 1


def test_garbage_tail_and_bad_cursor_file(tmp_path: Path) -> None:
    d, seg = _one_segment(tmp_path)
    with Outbox(d) as ob:
        ob.ack(30)
    with open(seg, "ab") as f:
        f.write(random.Random(3).randbytes(3000) + fmt.REC_MAGIC + b"\x00" * 40)
    (d / "cursor").write_bytes(b"\xff" * 600)  # the cursor is unreadable: all pending again
    with Outbox(d) as ob:
        assert ob.corrupt == 2 and ob.acked == 0
        assert [s for s, _ in everything(ob)] == list(range(1, 101))
        assert ob.next_seq == 101


def test_foreign_file_in_the_directory_is_an_error_naming_it(tmp_path: Path) -> None:
    d, _seg = _one_segment(tmp_path)
    (d / f"{'9' * 20}.seg").write_bytes(b"not a segment at all, but long enough")
    with pytest.raises(OutboxError, match=r"99999999999999999999\.seg is not an outbox segment"):
        Outbox(d)
    Path(d / f"{'9' * 20}.seg").unlink()
    Outbox(d).close()  # the failed open released the lock


# -- the disk budget -----------------------------------------------------------


def test_drop_oldest_counts_drops_and_keeps_the_newest(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8192, segment_bytes=2048)
    with Outbox(d, limits) as ob:
        fill(ob, 1000)
        assert ob.bytes_used <= limits.max_bytes
        assert ob.dropped > 0 and ob.dropped + ob.depth == 1000
        ob.flush()
        got = everything(ob)
        assert [s for s, _ in got] == list(range(1001 - ob.depth, 1001))
        dropped = ob.dropped
    with Outbox(d, limits) as ob:
        assert ob.dropped == dropped and ob.stats()["dropped"] == dropped
        assert [s for s, _ in everything(ob)] == [s for s, _ in got]


def test_refuse_raises_outbox_full_and_loses_nothing(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8192, segment_bytes=2048, policy="refuse")
    with Outbox(d, limits) as ob:
        accepted = []
        with pytest.raises(OutboxFull, match="max_bytes=8192") as info:
            for _ in range(1000):
                accepted.append(ob.append(payload(ob.next_seq), 0.0))
        assert isinstance(info.value, OutboxError) and isinstance(info.value, OSError)
        assert 50 < len(accepted) < 1000 and ob.dropped == 0 and ob.depth == len(accepted)
        with pytest.raises(OutboxFull):
            ob.append(b"x", 0.0)
        ob.flush()
        assert [s for s, _ in everything(ob)] == accepted
        ob.ack(accepted[len(accepted) // 2])  # delivery frees room
        assert ob.append(b"x", 0.0) == accepted[-1] + 1
    with Outbox(d, limits) as ob:
        rest = accepted[len(accepted) // 2 + 1 :]
        assert [s for s, _ in everything(ob)] == [*rest, accepted[-1] + 1]


# -- a disk that fills, for real -----------------------------------------------


@pytest.fixture
def tiny_fs(tmp_path: Path) -> Any:
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=192k", "tmpfs", str(mnt)], capture_output=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def _fill_disk(ob: Outbox) -> tuple[list[int], int, OutboxError]:
    accepted: list[int] = []
    flushed = 0
    try:
        for i in range(100_000):
            accepted.append(ob.append(payload(ob.next_seq) * 3, float(i)))
            if ob.flush_due(float(i)) or i % 50 == 49:
                ob.flush()
                flushed = ob.durable_seq
    except OutboxError as exc:
        return accepted, flushed, exc
    raise AssertionError("the disk never filled")


def test_disk_full_is_a_clear_error_and_loses_nothing_accepted(tiny_fs: Path) -> None:
    d = tiny_fs / "ob"
    limits = OutboxLimits(max_bytes=1 << 30, segment_bytes=16384)
    ob = Outbox(d, limits)
    accepted, flushed, exc = _fill_disk(ob)
    everyone = list(accepted)
    assert exc.errno == errno.ENOSPC and "disk is full" in str(exc) and str(d) in str(exc)
    assert flushed > 100
    with pytest.raises(OutboxError, match="disk is full"):  # refused while full
        ob.append(b"more", 0.0)
    with pytest.raises(OutboxError, match="disk is full"):
        ob.flush()
    ob.ack(flushed // 2)  # the broker took some: their segments go, space is back
    ob.flush()  # now what was accepted is written
    assert [s for s, _ in everything(ob)] == [s for s in accepted if s > flushed // 2]
    # fill it again, then give up: close fails, the flushed records are all there
    accepted, flushed, exc = _fill_disk(ob)
    everyone += accepted
    assert exc.errno == errno.ENOSPC
    with pytest.raises(OutboxError, match="disk is full"):
        ob.close()
    assert ob.closed
    with Outbox(d, limits) as again:  # reopening on a full disk works
        got = everything(again)
        assert [s for s, _ in got if s <= flushed] == [
            s for s in everyone if again.acked < s <= flushed
        ]
        assert all(rec == payload(s) * 3 for s, rec in got)
        again.ack(again.next_seq - 1)


# -- the lock -----------------------------------------------------------------


def test_second_outbox_on_the_same_directory_is_refused(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    holder = textwrap.dedent(
        """
        import sys
        from pyrtu.bridge.outbox import Outbox
        ob = Outbox(sys.argv[1])
        print("locked", flush=True)
        sys.stdin.read()
        ob.close()
        """
    )
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-c", holder, str(d)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline() == b"locked\n"
        with pytest.raises(OutboxError, match=f"outbox directory {d} is in use"):
            Outbox(d)
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
    with Outbox(d) as ob:  # released with the process
        with pytest.raises(OutboxError, match="in use"):
            Outbox(d)  # and in the same process too
        assert ob.depth == 0


# -- bounded memory -----------------------------------------------------------


def test_memory_stays_bounded_with_two_million_records_unacked(tmp_path: Path) -> None:
    """The broker is down: 2 million records pile up; the process does not grow.

    Measured in a child process (its own peak RSS) rather than with tracemalloc, which
    would slow 2 million appends tenfold; Python objects alive are counted too.
    """
    r = run_child(
        """
        import gc, sys
        from pyrtu.bridge.outbox import Outbox, OutboxLimits

        def rss(field):
            for line in open("/proc/self/status"):
                if line.startswith(field):
                    return int(line.split()[1]) * 1024
            raise LookupError(field)

        ob = Outbox(sys.argv[1], OutboxLimits(segment_bytes=4 << 20))
        rec = b"r" * 20
        for i in range(20_000):  # warm up: first segments, index arrays, buffers
            ob.append(rec, float(i))
        ob.flush()
        ob.pending(1000)
        gc.collect()
        base_rss, base_blocks = rss("VmRSS:"), sys.getallocatedblocks()
        for i in range(2_000_000):
            ob.append(rec, float(i))
            if ob.flush_due(0.0):
                ob.flush()
        ob.flush()
        assert len(ob.pending(1000, after=1_000_000)) == 1000
        assert ob.oldest_time == 0.0 and ob.depth == 2_020_000, ob.stats()
        gc.collect()
        print(rss("VmHWM:") - base_rss, sys.getallocatedblocks() - base_blocks, ob.bytes_used)
        """,
        str(tmp_path / "ob"),
    )
    assert r.returncode == 0, r.stderr.decode()
    peak_growth, blocks, used = (int(x) for x in r.stdout.split())
    assert used > 2_000_000 * 48  # the backlog is on disk ...
    assert peak_growth < 8 << 20, f"peak RSS grew by {peak_growth} bytes"  # ... not in memory
    assert blocks < 2000, f"{blocks} more Python objects alive"


# -- bad arguments -------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "exc", "name"),
    [
        ({"max_bytes": 1.5}, TypeError, "max_bytes"),
        ({"max_bytes": 4096, "segment_bytes": 4096}, ValueError, "max_bytes"),
        ({"segment_bytes": "8M"}, TypeError, "segment_bytes"),
        ({"segment_bytes": 100}, ValueError, "segment_bytes"),
        ({"fsync_interval": "1"}, TypeError, "fsync_interval"),
        ({"fsync_interval": -1.0}, ValueError, "fsync_interval"),
        ({"fsync_interval": float("nan")}, ValueError, "fsync_interval"),
        ({"fsync_records": 0}, ValueError, "fsync_records"),
        ({"fsync_records": True}, TypeError, "fsync_records"),
        ({"policy": "drop-newest"}, ValueError, "policy"),
        ({"policy": None}, TypeError, "policy"),
    ],
)
def test_bad_limits_name_the_field(kwargs: dict[str, Any], exc: type[Exception], name: str) -> None:
    with pytest.raises(exc, match=name):
        OutboxLimits(**kwargs)


def test_bad_arguments_name_the_argument(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="directory"):
        Outbox(42)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="limits"):
        Outbox(tmp_path / "a", limits={"max_bytes": 1})  # type: ignore[arg-type]
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutboxError, match=str(tmp_path / "file")):
        Outbox(tmp_path / "file")
    with Outbox(tmp_path / "ob", SMALL) as ob:
        with pytest.raises(TypeError, match="record"):
            ob.append("text", 0.0)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="record is 4097 bytes"):
            ob.append(bytes(4097), 0.0)
        with pytest.raises(TypeError, match="now"):
            ob.append(b"x", "0")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="now"):
            ob.append(b"x", float("inf"))
        ob.append(bytearray(b"ok"), 0.0)
        ob.flush()
        with pytest.raises(TypeError, match="limit"):
            ob.pending(1.0)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="limit"):
            ob.pending(-1)
        with pytest.raises(TypeError, match="after"):
            ob.pending(1, after="0")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="after"):
            ob.pending(1, after=-1)
        with pytest.raises(TypeError, match="seq"):
            ob.ack("1")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="seq"):
            ob.ack(2)  # never appended
        with pytest.raises(ValueError, match="seq"):
            ob.ack(-1)
        assert ob.pending(0) == [] and ob.pending(5) == [(1, b"ok")]
    with pytest.raises(ValueError, match="closed"):
        ob.append(b"x", 0.0)
    ob.close()  # idempotent


# -- the sequence and ack invariants, by hypothesis ------------------------------

OPS = st.lists(
    st.one_of(
        st.tuples(st.just("append"), st.integers(0, 300), st.integers(1, 40)),
        st.tuples(st.just("flush"), st.just(0), st.just(0)),
        st.tuples(st.just("ack"), st.integers(0, 10_000), st.just(0)),
        st.tuples(st.just("pending"), st.integers(0, 50), st.integers(-1, 400)),
        st.tuples(st.just("reopen"), st.just(0), st.just(0)),
    ),
    max_size=40,
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=OPS, policy=st.sampled_from(["drop-oldest", "refuse"]))
def test_sequence_and_ack_invariants(ops: list[tuple[str, int, int]], policy: str) -> None:
    limits = OutboxLimits(max_bytes=6144, segment_bytes=2048, policy=policy)  # type: ignore[arg-type]
    d = Path(tempfile.mkdtemp(prefix="obx-"))
    try:
        ob = Outbox(d, limits)
        model: list[tuple[int, bytes]] = []  # every record accepted, in order
        by_ack = 0  # records released by the caller's acks (not by drops)
        last_seq = 0
        for op, a, b in ops:
            if op == "append":
                for i in range(b):
                    rec = bytes([i]) * (a % 200)
                    try:
                        seq = ob.append(rec, float(i))
                    except OutboxFull:
                        assert policy == "refuse"
                        break
                    assert seq > last_seq
                    last_seq = seq
                    model.append((seq, rec))
            elif op == "flush":
                ob.flush()
                assert ob.durable_seq == ob.next_seq - 1
            elif op == "ack" and model:
                seq = min(a, ob.next_seq - 1)
                by_ack += sum(1 for s, _ in model if ob.acked < s <= seq)
                ob.ack(seq)
            elif op == "pending":
                after = None if b < 0 else b
                got = ob.pending(a, after=after)
                start = max(ob.acked, after or 0)
                want = [r for r in model if start < r[0] <= ob.durable_seq][:a]
                assert got == want
            elif op == "reopen":
                ob.close()
                ob = Outbox(d, limits)
                assert ob.next_seq == last_seq + 1 or not model
            assert ob.depth == sum(1 for s, _ in model if s > ob.acked)
            assert len(model) == ob.depth + ob.dropped + by_ack
            if policy == "refuse":
                assert ob.dropped == 0
            assert ob.bytes_used <= limits.max_bytes
        ob.close()
    finally:
        shutil.rmtree(d)
