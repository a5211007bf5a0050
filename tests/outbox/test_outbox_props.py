"""The outbox's sequence and ack invariants, by hypothesis: random appends, flushes,
acks, reads with a publish cursor and reopens against a model, under both budget
policies (pyrtu.outbox.outbox)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pyrtu.outbox.outbox import Outbox, OutboxFull, OutboxLimits

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
