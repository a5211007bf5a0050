"""The virtual bus's sans-I/O schedule: csrc/rtu_vbus.c and its twin pyrtu/core/_pure/vbus.py.

Synthetic time (integer ns) in, deliveries out: no pty, no clock.  The two must agree
on every output (bytes per drop, deadlines, unplugs due, counters) and on the
exception type of every refused input; the semantics are pinned here on both.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from c_core import need_c
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pyrtu.core._pure.vbus import OUT, QUEUE, Schedule
from pyrtu.vbus import collision_byte

C = 86_806  # ns: a 10-bit character at 115200 baud
LEAD = 40_000

Sched = Any  # Schedule or CSchedule: the same interface


def _c_schedule() -> Callable[[int, int, int], Sched]:
    need_c()
    from pyrtu.vbus._cvbus import CSchedule

    return CSchedule


@pytest.fixture(params=["c", "python"])
def make(request: pytest.FixtureRequest) -> Callable[[int, int, int], Sched]:
    """The schedule class of each backend in turn."""
    return _c_schedule() if request.param == "c" else Schedule


def plugged(make: Callable[[int, int, int], Sched], n: int = 3, lead: int = LEAD) -> Sched:
    s = make(n, C, lead)
    for i in range(n):
        s.plug(i)
    return s


def drain(s: Sched, n: int) -> list[bytes]:
    out = []
    for i in range(n):
        out.append(s.take_output(i))
        s.written(i, len(out[-1]), 1)
    return out


def test_a_character_is_delivered_when_its_last_bit_is_sent(make: Any) -> None:
    s = plugged(make, 3, lead=0)
    s.transmit(0, b"\x01\x02", 1_000)
    assert s.deadline() == 1_000 + C
    assert s.service(1_000 + C - 1) == [] and drain(s, 3) == [b"", b"", b""]
    s.service(1_000 + C)
    assert drain(s, 3) == [b"", b"\x01", b"\x01"]  # not to the sender (no echo)
    assert s.deadline() == 1_000 + 2 * C
    s.service(1_000 + 2 * C)
    assert drain(s, 3) == [b"", b"\x02", b"\x02"]
    assert s.deadline() is None and not s.busy()


def test_deliveries_are_due_lead_early(make: Any) -> None:
    s = plugged(make, 2)
    s.transmit(0, b"A", 0)
    assert s.deadline() == C - LEAD
    s.service(C - LEAD)
    assert drain(s, 2) == [b"", b"A"]


def test_echo_and_unplugged_receivers(make: Any) -> None:
    s = plugged(make, 3, lead=0)
    s.set_echo(0, True)
    s.unplug(2)
    s.transmit(0, b"xy", 0)
    s.service(2 * C)
    assert drain(s, 3) == [b"xy", b"xy", b""]
    s.transmit(2, b"z", 3 * C)  # an unplugged drop transmits nothing
    assert s.deadline() is None


def test_overlapping_characters_collide(make: Any) -> None:
    s = plugged(make, 3, lead=0)
    s.transmit(0, b"\x0f\x00", 0)
    s.transmit(1, b"\xf0", C // 2)
    s.service(10 * C)
    got = drain(s, 3)
    # in wire order: 0x0F at 0 (hits 0xF0 queued at C/2), 0xF0 at C/2 (hits 0x0F),
    # 0x00 at C (hits 0xF0, still on the wire until 1.5 C)
    want = [collision_byte(0x0F, 0xF0), collision_byte(0xF0, 0x0F), collision_byte(0x00, 0xF0)]
    assert got[2] == bytes(want)
    assert s.collisions == 1 and s.collided == 3 and s.wire_bytes == 3
    assert s.drop_counters(0)["collisions"] == s.drop_counters(1)["collisions"] == 1
    assert s.drop_counters(0)["collided_bytes"] == 2


def test_a_reply_starts_after_the_byte_it_answers(make: Any) -> None:
    """Causality: the latency compensation cannot make a reply overlap its cause."""
    s = plugged(make, 2)
    s.transmit(0, b"Q", 0)
    s.service(C - LEAD)  # delivered `lead` early
    drain(s, 2)
    s.transmit(1, b"R", C - LEAD)  # the client answers at once
    assert s.queued(1) == [(C, ord("R"))]
    s.service(2 * C)
    assert drain(s, 2)[0] == b"R" and s.collisions == 0


def test_unplug_after_bytes_and_cut(make: Any) -> None:
    s = plugged(make, 2, lead=0)
    s.set_unplug_after(0, 3)
    s.transmit(0, b"abcdef", 0)
    assert [b for _, b in s.queued(0)] == list(b"abc")
    assert s.deadline() == C  # the first delivery comes before the unplug at 3 C
    assert s.service(3 * C - 1) == []
    assert s.service(3 * C) == [0]
    assert drain(s, 2)[1] == b"abc"
    s.cut(1, 5 * C)
    s.transmit(1, b"late", 4 * C)  # cut: nothing more goes on the wire
    assert s.deadline() == 5 * C and s.service(5 * C) == [1]


def test_batch_holds_then_releases(make: Any) -> None:
    s = plugged(make, 2, lead=0)
    s.set_batch(1, 5 * C, 3)
    s.transmit(0, b"12345", 0)
    s.service(2 * C)
    assert drain(s, 2)[1] == b""  # held
    s.service(3 * C)
    assert drain(s, 2)[1] == b"123"  # batch_bytes reached
    s.service(5 * C)
    assert drain(s, 2)[1] == b""
    assert s.deadline() == 4 * C + 5 * C  # 5 C after the first held byte arrived
    s.service(9 * C)
    assert drain(s, 2)[1] == b"45"
    assert s.drop_counters(1)["batches"] == 2


def test_any_bytes_like_and_what_is_held(make: Any) -> None:
    s = plugged(make, 2, lead=0)
    s.set_batch(1, 10 * C, 100)
    s.transmit(0, bytearray(b"ab"), 0)
    s.transmit(0, memoryview(b"xcdx")[1:3], 0)
    s.service(4 * C)
    assert s.held(1) == b"abcd" and drain(s, 2) == [b"", b""]


def test_counters_of_writes(make: Any) -> None:
    s = plugged(make, 3, lead=0)
    s.transmit(0, b"abc", 0)
    s.service(3 * C)
    assert s.take_output(1) == b"abc"
    s.written(1, 2, 1)  # the client's buffer took two
    s.written(2, 0, 0)  # nobody listens on drop 2
    c1, c2 = s.drop_counters(1), s.drop_counters(2)
    assert (c1["rx_bytes"], c1["overruns"], c2["unheard"]) == (2, 1, 3)
    assert s.drop_counters(0)["tx_bytes"] == 3


def test_bounded_queue_and_output(make: Any) -> None:
    s = plugged(make, 2, lead=0)
    assert s.space(0) == QUEUE
    with pytest.raises(BufferError):
        s.transmit(0, bytes(QUEUE + 1), 0)
    s.transmit(0, bytes(QUEUE), 0)
    assert s.space(0) == 0
    s.service(QUEUE * C)  # a late hub: everything due at once
    assert len(s.take_output(1)) == OUT
    assert s.drop_counters(1)["overruns"] == QUEUE - OUT


@pytest.mark.parametrize(
    ("call", "exc"),
    [
        (lambda s: s.transmit(5, b"x", 0), IndexError),
        (lambda s: s.transmit(-1, b"x", 0), IndexError),
        (lambda s: s.transmit(0, b"x", 2**63), ValueError),
        (lambda s: s.transmit(0, b"x", 1.5), TypeError),
        (lambda s: s.service(-(2**63)), ValueError),
        (lambda s: s.set_batch(0, -1, 10), ValueError),
        (lambda s: s.set_batch(0, 10, OUT + 1), ValueError),
        (lambda s: s.set_batch(0, 10, 0), ValueError),
        (lambda s: s.written(0, 1, 1), ValueError),
        (lambda s: s.cut(0, 2**62 + 1), ValueError),
        (lambda s: s.set_echo("0", True), TypeError),
        (lambda s: s.transmit(0, "text", 0), TypeError),
        (lambda s: s.transmit(0, [1, 2], 0), TypeError),
    ],
)
def test_refused_inputs_raise_the_same_on_both(
    make: Any, call: Callable[[Sched], object], exc: type[Exception]
) -> None:
    s = plugged(make, 2)
    with pytest.raises(exc):
        call(s)


@pytest.mark.parametrize(
    ("args", "exc"),
    [((0, C, 0), ValueError), ((249, C, 0), ValueError), ((2, 0, 0), ValueError),
     ((2, C, -1), ValueError), ((2, C, 10**8), ValueError), ((2.0, C, 0), TypeError)],
)  # fmt: skip
def test_bad_configurations(make: Any, args: tuple[Any, ...], exc: type[Exception]) -> None:
    with pytest.raises(exc):
        make(*args)


# -- agreement: random operation sequences through both --------------------------------

op = st.one_of(
    st.tuples(st.just("tx"), st.integers(0, 3), st.binary(max_size=40), st.integers(0, 30 * C)),
    st.tuples(st.just("svc"), st.integers(0, 60 * C)),
    st.tuples(st.just("echo"), st.integers(0, 3), st.booleans()),
    st.tuples(st.just("batch"), st.integers(0, 3), st.integers(0, 20 * C), st.integers(1, 64)),
    st.tuples(st.just("after"), st.integers(0, 3), st.integers(-1, 20)),
    st.tuples(st.just("cut"), st.integers(0, 3), st.integers(0, 40 * C)),
    st.tuples(st.just("hold"), st.integers(0, 3)),
    st.tuples(st.just("plug"), st.integers(0, 3), st.booleans()),
    st.tuples(st.just("write"), st.integers(0, 3), st.integers(-1, 1), st.integers(0, 50)),
)


def run_ops(s: Sched, ops: list[tuple[Any, ...]]) -> list[object]:
    """Apply `ops` (time only moves forward) and record every observable output."""
    log: list[object] = []
    now = 0
    for o in ops:
        kind = o[0]
        try:
            if kind == "tx":
                now += o[3] // 8
                s.transmit(o[1], o[2], now)
            elif kind == "svc":
                now += o[1]
                log.append(("due", s.service(now)))
            elif kind == "echo":
                s.set_echo(o[1], o[2])
            elif kind == "batch":
                s.set_batch(o[1], o[2], o[3])
            elif kind == "after":
                s.set_unplug_after(o[1], o[2])
            elif kind == "cut":
                s.cut(o[1], now + o[2])
            elif kind == "hold":
                s.clear_hold(o[1])
            elif kind == "plug":
                (s.plug if o[2] else s.unplug)(o[1])
            elif kind == "write":
                out = s.take_output(o[1])
                s.written(o[1], min(o[3], len(out)), o[2])
                log.append(("out", o[1], out))
        except Exception as exc:  # the exception type is an output too
            log.append(("raised", kind, type(exc).__name__))
        log.append((s.deadline(), s.busy()))
    log.append([s.drop_counters(i) for i in range(4)])
    log.append((s.wire_bytes, s.collisions, s.collided, [s.queued(i) for i in range(4)]))
    return log


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(op, max_size=60), lead=st.sampled_from([0, LEAD]))
def test_c_and_twin_agree(ops: list[tuple[Any, ...]], lead: int) -> None:
    c_schedule = _c_schedule()
    results = []
    for make in (c_schedule, Schedule):
        s = make(4, C, lead)
        for i in range(4):
            s.plug(i)
        results.append(run_ops(s, ops))
    assert results[0] == results[1]
