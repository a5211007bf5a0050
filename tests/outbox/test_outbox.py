"""The bridge's durable outbox (pyrtu.outbox.outbox): a bounded, checksummed on-disk log.

Crashes are real (a child process SIGKILLed at random points), a full disk is a real
tiny tmpfs, the lock is held by another process.
"""

from __future__ import annotations

import array
import contextlib
import errno
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
from outbox_helpers import SMALL, everything, fill, payload, run_child, segments

from pyrtu.outbox.outbox import Outbox, OutboxError, OutboxFull, OutboxLimits

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
        from pyrtu.outbox.outbox import Outbox, OutboxLimits
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
        assert ob.oldest_time == 10.0  # read from the bytes not yet written
        assert ob.flush_at == 10.5 and not ob.flush_due(10.49) and ob.flush_due(10.5)
        ob.append(b"b", 10.1)
        ob.append(b"c", 10.2)
        assert ob.flush_due(10.2) and ob.flush_at == 10.0
        ob.flush()
        assert ob.flush_at is None and not ob.flush_due(99.0)


def test_fsync_is_batched_one_per_flush_not_per_record(tmp_path: Path) -> None:
    """The syscalls, counted with strace: 10,000 appends flushed every 1,000."""
    strace = shutil.which("strace")
    if strace is None:
        pytest.skip("strace is not installed (apt-get install strace)")
    code = textwrap.dedent(
        """
        import os, sys
        from pyrtu.outbox.outbox import Outbox, OutboxLimits
        ob = Outbox(sys.argv[1], OutboxLimits(fsync_records=1000))
        os.write(1, b"BEGIN\\n")
        for i in range(10_000):
            ob.append(b"x" * 200, 0.0)
            if ob.flush_due(0.0):
                ob.flush()
        os.write(1, b"END\\n")
        ob.close()
        """
    )
    trace = tmp_path / "trace"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    r = subprocess.run(
        [strace, "-f", "-e", "trace=fdatasync,fsync,write", "-e", "signal=none",
         "-o", str(trace), sys.executable, "-c", code, str(tmp_path / "ob")],
        capture_output=True, env=env,
    )  # fmt: skip
    if r.returncode != 0 and b"ptrace" in r.stderr:
        pytest.skip(f"strace cannot trace here: {r.stderr.decode().strip()}")
    assert r.returncode == 0 and r.stdout == b"BEGIN\nEND\n", r.stderr
    lines = trace.read_text().splitlines()
    begin = next(i for i, ln in enumerate(lines) if "BEGIN" in ln)
    end = next(i for i, ln in enumerate(lines) if "END" in ln)
    syncs = [ln for ln in lines[begin:end] if "fdatasync(" in ln]
    # ten flushes, each one fdatasync of the segment; the block of sequence
    # numbers is reserved in the cursor file when the outbox opens (before BEGIN),
    # and again by a flush once half of it is used (not within 10,000 appends)
    assert len(syncs) == 10, syncs
    assert any("fdatasync(" in ln for ln in lines[:begin])


# -- crash safety for real: SIGKILL at random points --------------------------

CHILD = textwrap.dedent(
    """
    import hashlib, os, random, sys
    from pyrtu.outbox.outbox import Outbox, OutboxLimits

    def payload(seq):
        digest = hashlib.blake2b(str(seq).encode(), digest_size=32).digest()
        return (digest * 2)[: 1 + seq % 64]

    rng = random.Random(int(sys.argv[2]))
    ob = Outbox(sys.argv[1], OutboxLimits(max_bytes=int(sys.argv[3]), segment_bytes=8192))
    os.write(1, b"R %d\\n" % ob.next_seq)
    while True:
        for _ in range(rng.choice((rng.randint(1, 50), rng.randint(1, 3000)))):
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


def _run_child_and_kill(d: Path, seed: int, rng: random.Random, budget: int) -> list[list[int]]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(d), str(seed), str(budget)],
        stdout=subprocess.PIPE,
        env=env,
    )
    assert proc.stdout is not None
    first = proc.stdout.readline()  # opened: now let it run a random while ...
    assert first.startswith(b"R "), first
    if rng.random() < 0.5:
        time.sleep(rng.uniform(0.0, 0.4))
    else:  # ... or until it has appended a random number of records (mid-batch)
        count, target = 0, rng.randint(1, 20_000)
        while count < target:
            line = proc.stdout.readline()
            first += line
            count += line.startswith(b"A ")
            if not line:
                break
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
    for rnd in range(12):
        # odd rounds: a budget of 8 segments, so the oldest are dropped as it runs
        budget = 1 << 16 if rnd % 2 else 1 << 26
        events = _run_child_and_kill(d, rnd, rng, budget)
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
            assert max(acked_at_flush, acked_floor) <= ob.acked
            assert ob.acked <= (max(acks) if budget > 1 << 16 else handed[-1])
            got = everything(ob)
            for seq, rec in got:
                assert rec == payload(seq) and seq > ob.acked
            got_seqs = {s for s, _ in got}
            # records the child acked may be gone with their segments even if the kill
            # came before the ack cursor was flushed: they were delivered (dropped
            # ones are below the cursor: a drop writes it at once)
            floor = max(ob.acked, *acks)
            must = [s for s in sorted(kept) + mine if floor < s and (s in kept or s <= flushed)]
            missing = [s for s in must if s not in got_seqs]
            assert missing == [], f"round {rnd}: flushed records lost: {missing[:10]}"
            # what is back beyond the last flush is a prefix of the unflushed batch
            tail = [s for s in mine if s > max(flushed, ob.acked)]  # (not dropped)
            extra = sorted(s for s in got_seqs if s in tail)
            assert extra == tail[: len(extra)]
            assert got_seqs <= kept | set(mine)  # nothing that was never appended
            if rnd % 3 == 2 and got:
                ob.ack(got[len(got) // 2][0])  # a broker took some
            acked_floor = ob.acked
            kept = {s for s in got_seqs if s > ob.acked}
    assert len(handed) > 500  # the children did work between the kills


# -- the disk budget -----------------------------------------------------------


def test_drop_oldest_counts_drops_and_keeps_the_newest(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8192, segment_bytes=2048)
    with Outbox(d, limits) as ob:
        for _ in range(1000):
            ob.append(payload(ob.next_seq), 0.0)
            assert ob.bytes_used <= limits.max_bytes
        assert ob.dropped > 0 and ob.dropped + ob.depth == 1000
        ob.flush()
        got = everything(ob)
        assert [s for s, _ in got] == list(range(1001 - ob.depth, 1001))
        dropped = ob.dropped
    with Outbox(d, limits) as ob:
        assert ob.dropped == dropped and ob.stats()["dropped"] == dropped
        assert [s for s, _ in everything(ob)] == [s for s, _ in got]


def test_drops_are_counted_on_disk_at_once(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    r = run_child(
        """
        import os, signal, sys
        from pyrtu.outbox.outbox import Outbox, OutboxLimits
        ob = Outbox(sys.argv[1], OutboxLimits(max_bytes=8192, segment_bytes=2048))
        while ob.dropped == 0:
            ob.append(b"x" * 40, 0.0)
        print(ob.dropped, ob.acked, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)  # no flush: the drop was written already
        """,
        str(d),
    )
    assert r.returncode == -signal.SIGKILL, r.stderr
    dropped, acked = (int(x) for x in r.stdout.split())
    with Outbox(d, OutboxLimits(max_bytes=8192, segment_bytes=2048)) as ob:
        assert dropped > 0 and ob.dropped == dropped and ob.acked == acked


def test_refuse_raises_outbox_full_and_loses_nothing(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    limits = OutboxLimits(max_bytes=8192, segment_bytes=2048, policy="refuse")
    with Outbox(d, limits) as ob:
        accepted = []
        with pytest.raises(OutboxFull, match="max_bytes=8192") as info:
            for _ in range(1000):
                accepted.append(ob.append(payload(ob.next_seq), 0.0))
                assert ob.bytes_used <= limits.max_bytes
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


def test_a_full_outbox_refuses_until_delivery_frees_a_segment(tmp_path: Path) -> None:
    """Once full (policy "refuse"), a record that would still fit the bytes left is
    refused too, until an acknowledgement frees a segment: the outbox does not flap
    between full and accepting (each flip a report to the user)."""
    limits = OutboxLimits(max_bytes=8192, segment_bytes=2048, policy="refuse")
    with Outbox(tmp_path / "ob", limits) as ob:
        big = b"b" * 100  # 28-byte record header + 100: 128 bytes, 15 to a segment
        accepted = []
        with pytest.raises(OutboxFull):
            for _ in range(100):
                accepted.append(ob.append(big, 0.0))
        # four segments of 16 + 15 * 128 = 1936 bytes, then 16 + 3 * 128 in the fifth:
        # 8144 bytes used, 48 left (a record of 20 bytes would fit exactly)
        assert len(accepted) == 63 and ob.bytes_used == 8144
        fits = b"s" * (limits.max_bytes - ob.bytes_used - 28)
        with pytest.raises(OutboxFull):
            ob.append(fits, 0.0)
        ob.flush()
        ob.ack(accepted[20])  # the first segment's 15 records delivered: it goes
        assert ob.bytes_used == 8144 - 1936
        assert ob.append(fits, 0.0) == accepted[-1] + 1


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
    finally:  # lazily if a failed test left a file open there
        if subprocess.run(["umount", str(mnt)], capture_output=True).returncode:
            subprocess.run(["umount", "-l", str(mnt)], check=True)


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
    try:
        accepted, flushed, exc = _fill_disk(ob)
        everyone = list(accepted)
        assert exc.errno == errno.ENOSPC and str(exc).startswith(f"outbox {d}: the disk is full")
        assert "records already accepted are kept" in str(exc)
        assert flushed > 100 and accepted[-1] > flushed  # some accepted, not yet written
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
    finally:
        with contextlib.suppress(OutboxError):
            ob.close()  # (a failed assertion must not leave the tmpfs busy)


# -- the lock -----------------------------------------------------------------


def test_second_outbox_on_the_same_directory_is_refused(tmp_path: Path) -> None:
    d = tmp_path / "ob"
    holder = textwrap.dedent(
        """
        import sys
        from pyrtu.outbox.outbox import Outbox
        ob = Outbox(sys.argv[1])
        print("locked", flush=True)
        sys.stdin.read()
        ob.close()
        """
    )
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
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


@pytest.mark.rss
def test_memory_stays_bounded_with_two_million_records_unacked(tmp_path: Path) -> None:
    """The broker is down: 2 million records pile up; the process does not grow.

    Measured in a child process (its own peak RSS) rather than with tracemalloc, which
    would slow 2 million appends tenfold; Python objects alive are counted too.
    """
    r = run_child(
        """
        import gc, sys
        from pyrtu.outbox.outbox import Outbox, OutboxLimits

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
        ob.append(memoryview(array.array("H", [1, 2])), 0.0)  # 2 items, 4 bytes
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
            ob.ack(3)  # never appended
        with pytest.raises(ValueError, match="seq"):
            ob.ack(-1)
        assert ob.pending(0) == [] and ob.pending(5) == [(1, b"ok"), (2, b"\x01\x00\x02\x00")]
    with pytest.raises(ValueError, match="closed"):
        ob.append(b"x", 0.0)
    ob.close()  # idempotent
