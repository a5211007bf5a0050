"""The bus scheduler with a fake clock (no sleeps, no ports): deadlines, preemption
by writes, holes learned from exception 2, the overload report, slave health with
back-off and its share of the bus, the figures."""

from __future__ import annotations

import itertools
import time
from collections import Counter
from collections.abc import Callable, Sequence

import pytest

from pyrtu.pdu.errors import ExceptionResponseError, FrameError, NoResponseError
from pyrtu.poller import (
    BusScheduler,
    Limits,
    Overload,
    Point,
    PointDropped,
    ScheduledRequest,
    SlaveState,
    Update,
    Wire,
)
from pyrtu.poller.events import Event, Tracker, Unchanged

WIRE = Wire(11 / 19200, 0.002005, 0.002005)
TIMEOUT = 0.1


def pt(address: int, name: str | None = None, **kw: object) -> Point:
    fields: dict[str, object] = dict(bus="b", slave=1, table="holding", interval=1.0)
    fields.update(kw)
    return Point(name or f"s{fields['slave']}.{address}", address=address, **fields)  # type: ignore[arg-type]


Outcome = Sequence[int] | Sequence[bool] | BaseException | None


class FakeBus:
    """Runs a scheduler against a model of the slaves on a fake clock: a transaction
    lasts its wire time (answered) or the timeout (no answer); the t3.5 silence
    before a request is waited only where the line was not quiet that long."""

    def __init__(self, sched: BusScheduler, registers: dict[int, dict[int, int]] | None = None):
        self.sched = sched
        self.now = 0.0
        self.regs = registers or {}
        self.dead: set[int] = set()
        self.done: list[tuple[ScheduledRequest, float, float, str]] = []
        self.events: list[Event | Unchanged] = []
        self.quiet_since = -1.0

    def answer(self, req: ScheduledRequest) -> tuple[Outcome, float]:
        if req.slave in self.dead:
            return NoResponseError("no answer", req.slave, req.function), TIMEOUT
        cost = WIRE.read(req.table, req.count)
        if req.kind == "write":
            for i, v in enumerate(req.values):
                self.regs.setdefault(req.slave, {})[req.address + i] = int(v)
            return None, req.cost
        mapped = self.regs.get(req.slave)
        if mapped is None:
            return [0] * req.count, cost
        if any(a not in mapped for a in range(req.address, req.address + req.count)):
            return ExceptionResponseError(req.slave, req.function, 2), WIRE.frames(8, 5)
        return [mapped[a] for a in range(req.address, req.address + req.count)], cost

    def run(self, until: float, hook: Callable[[float], None] | None = None) -> None:
        while self.now < until:
            if hook is not None:
                hook(self.now)
            req = self.sched.next_request(self.now)
            if req is None:
                dl = self.sched.deadline()
                self.now = until if dl is None else max(self.now + 1e-6, min(dl, until))
                continue
            outcome, duration = self.answer(req)
            start = self.now
            wait = max(0.0, self.quiet_since + WIRE.t35 - self.now)
            self.now += duration - WIRE.t35 + wait
            self.quiet_since = self.now
            if isinstance(outcome, BaseException):
                self.events += self.sched.on_failure(req, outcome, self.now)
                kind = type(outcome).__name__
            else:
                self.events += self.sched.on_response(req, outcome, self.now)
                kind = "ok"
            self.done.append((req, start, self.now, kind))

    def polls(self, slave: int | None = None) -> Counter[int]:
        """Completed poll transactions by block address."""
        return Counter(
            r.address for r, _, _, k in self.done
            if r.kind == "poll" and (slave is None or r.slave == slave) and k == "ok"
        )  # fmt: skip


def test_deadlines_each_block_at_its_interval() -> None:
    points = [pt(0, interval=0.1), pt(100, interval=0.5), pt(0, slave=2, interval=1.0)]
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched)
    bus.run(10.0)
    polls = Counter((r.slave, r.address) for r, *_ in bus.done)
    assert polls[(1, 0)] in (100, 101)
    assert polls[(1, 100)] in (20, 21)
    assert polls[(2, 0)] in (10, 11)
    # never early: each start is at or after its due time (multiples of the interval)
    starts = [s for r, s, *_ in bus.done if (r.slave, r.address) == (1, 100)]
    assert all(s >= k * 0.5 - 1e-9 for k, s in enumerate(starts))
    assert all(s <= k * 0.5 + 0.05 for k, s in enumerate(starts))  # and not late
    assert sched.report(bus.now).overloaded is False
    assert sched.deadline() is not None


def test_earliest_deadline_first() -> None:
    sched = BusScheduler("b", [pt(0, interval=1.0), pt(200, interval=0.3)], WIRE)
    first = sched.next_request(0.0)
    second = sched.next_request(0.0)
    assert first is not None and second is not None
    # both due at 0: order by due time then declaration; afterwards by deadline
    assert {first.address, second.address} == {0, 200}
    sched.on_response(first, [0], 0.01)
    sched.on_response(second, [0], 0.02)
    assert sched.next_request(0.1) is None
    assert sched.deadline() == pytest.approx(0.3)
    nxt = sched.next_request(0.35)
    assert nxt is not None and nxt.address == 200


def test_writes_and_on_demand_reads_preempt_polls() -> None:
    sched = BusScheduler("b", [pt(0, interval=0.01)], WIRE)
    w = sched.submit_write(1, "holding", 682, [0x13])
    reads = sched.submit_read(1, "input", 0, 300)
    assert (w.function, w.kind) == (6, "write") and [r.count for r in reads] == [125, 125, 50]
    assert sched.deadline() == float("-inf")
    got = [sched.next_request(1.0) for _ in range(5)]
    assert [g.kind for g in got if g] == ["write", "read", "read", "read", "poll"]
    assert sched.submit_write(1, "coils", 0, [True, False]).function == 15
    assert sched.submit_write(1, "coils", 0, [True]).function == 5
    assert sched.submit_write(1, "holding", 0, [1, 2]).function == 16
    with pytest.raises(ValueError, match="table"):
        sched.submit_write(1, "input", 0, [1])
    with pytest.raises(ValueError, match="values"):
        sched.submit_write(1, "holding", 0, [])


def test_a_write_submitted_mid_run_goes_next() -> None:
    points = [pt(a * 20, interval=0.001) for a in range(10)]  # overloaded: always a poll due
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched)
    submitted: list[ScheduledRequest] = []

    def hook(now: float) -> None:
        if now > 0.5 and not submitted:
            submitted.append(sched.submit_write(1, "holding", 5, [42]))

    bus.run(1.0, hook)
    idx = next(i for i, (r, *_) in enumerate(bus.done) if r is submitted[0])
    start = bus.done[idx][1]
    before = [s for _, s, *_ in bus.done[:idx]]
    assert max(before) < start and bus.regs[1][5] == 42
    # it went out right after the transaction in flight when it was submitted
    assert bus.done[idx - 1][2] == start and bus.done[idx - 1][1] <= 0.5 + 0.05


def test_holes_learned_from_exception_2() -> None:
    mapped = {a: a for a in (0, 1, 2, 6, 7, 8, 20)}
    points = [pt(a) for a in (0, 1, 2, 6, 7, 8)] + [pt(10, "missing"), pt(20)]
    sched = BusScheduler("b", points, WIRE)
    assert [(b.address, b.count) for b in sched.blocks] == [(0, 21)]
    bus = FakeBus(sched, {1: mapped})
    bus.run(5.0)
    dropped = [e for e in bus.events if isinstance(e, PointDropped)]
    assert [d.point.name for d in dropped] == ["missing"]  # once
    assert sched.dropped == frozenset({"missing"})
    blocks = sorted((b.address, b.count) for b in sched.blocks)
    assert blocks == [(0, 3), (6, 3), (20, 1)]
    # after learning, every read succeeds; every good point updated every second
    late = [k for r, s, _, k in bus.done if s > 1.0]
    assert late and all(k == "ok" for k in late)
    # (read: an `Update`, or the block's `Unchanged` when it answered as before)
    got = Counter(e.point.name for e in bus.events if isinstance(e, Update))
    got.update(p.name for e in bus.events if isinstance(e, Unchanged) for p in e.points)
    assert set(got) == {f"s1.{a}" for a in (0, 1, 2, 6, 7, 8, 20)}
    assert min(got.values()) >= 4


def _learn(points: list[Point], mapped: set[int]) -> tuple[BusScheduler, FakeBus]:
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched, {1: {a: a for a in mapped}})
    bus.run(5.0)
    return sched, bus


def test_holes_learned_converge_to_the_fewest_requests() -> None:
    """The first cut goes at the widest gap (9..15); the hole is in the narrower one
    (5): the second exception 2 finds it inside the first cut's block, the first
    cut is withdrawn and 8..17 is read as one block again (two requests, not
    three)."""
    points = [pt(a) for a in (0, 1, 2, 8, 16, 17)]
    mapped = set(range(18)) - {5}
    sched, bus = _learn(points, mapped)
    assert sorted((b.address, b.count) for b in sched.blocks) == [(0, 3), (8, 10)]
    fails = [r for r, _, _, k in bus.done if k != "ok"]
    assert len(fails) == 2
    late = [k for r, s, _, k in bus.done if s > 1.0]
    assert late and all(k == "ok" for k in late)
    # holes in both gaps: both cuts stay (three blocks), learned in a bounded number
    # of exception responses
    sched, bus = _learn(points, mapped - {12})
    assert sorted((b.address, b.count) for b in sched.blocks) == [(0, 3), (8, 1), (16, 2)]
    assert sum(k != "ok" for *_, k in bus.done) <= 4
    # a hole in the wide gap only: one cut, proven by the halves
    sched, bus = _learn(points, set(range(18)) - {12})
    assert sorted((b.address, b.count) for b in sched.blocks) == [(0, 9), (16, 2)]


@pytest.mark.parametrize("seed", range(40))
def test_hole_learning_always_ends_at_the_fewest_requests(seed: int) -> None:
    """Random maps and point sets: after learning, every read succeeds and the
    blocks are exactly those `plan` makes when it knows every hole in advance."""
    import random

    from pyrtu.poller import Cuts, plan

    rnd = random.Random(seed)
    mapped = {a for a in range(60) if rnd.random() > 0.12}
    addrs = sorted(rnd.sample(sorted(mapped), 12))
    points = [pt(a) for a in addrs]
    if seed % 4 == 0:  # and a point that does not exist: dropped, its cuts withdrawn
        points.append(pt(rnd.choice(sorted(set(range(60)) - mapped)), "missing"))
    sched, bus = _learn(points, mapped)
    late = [k for r, s, _, k in bus.done if s > 2.0]
    assert late and all(k == "ok" for k in late)
    assert sched.dropped == ({"missing"} if seed % 4 == 0 else set())
    known = Cuts()
    for a, b in itertools.pairwise(addrs):
        if any(x not in mapped for x in range(a + 1, b)):
            known.add("b", 1, "holding", b)
    best = plan([p for p in points if p.name != "missing"], WIRE, cuts=known)
    assert sorted((b.address, b.count) for b in sched.blocks) == [
        (b.address, b.count) for b in best
    ]


def test_other_exceptions_keep_the_schedule() -> None:
    sched = BusScheduler("b", [pt(0, interval=0.1)], WIRE)
    req = sched.next_request(0.0)
    assert req is not None
    assert sched.on_failure(req, ExceptionResponseError(1, 3, 4), 0.01) == [
        SlaveState("b", 1, True, 0.01)
    ]
    assert sched.slave_stats()[1].exceptions == 1 and sched.blocks
    assert sched.next_request(0.1) is not None


def test_overload_reported_with_lagging_points() -> None:
    # 40 blocks of one register every 10 ms: ~13.7 ms of wire each at 19200
    points = [pt(a * 30, interval=0.01) for a in range(40)]
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched)
    bus.run(3.0)
    over = [e for e in bus.events if isinstance(e, Overload)]
    assert over and over[0].overloaded and over[0].load > 10
    report = sched.report(bus.now)
    assert report.overloaded and report.load == pytest.approx(over[-1].load, rel=0.2)
    assert report.utilisation > 0.99  # the fake bus never idles while work is due
    assert len(report.lagging) == 40
    # every block is still read, in turn (EDF under overload shares the wire)
    polls = bus.polls()
    assert len(polls) == 40 and max(polls.values()) - min(polls.values()) <= 1


def test_no_overload_under_capacity() -> None:
    points = [pt(a * 30, interval=1.0) for a in range(40)]
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched)
    bus.run(5.0)
    assert not any(isinstance(e, Overload) for e in bus.events)
    r = sched.report(bus.now)
    assert not r.overloaded and r.lagging == () and 0.5 < r.load < 0.6
    assert r.utilisation == pytest.approx(r.load, rel=0.05)


def alive_and_dead(dead: bool, until: float = 120.0) -> tuple[FakeBus, BusScheduler]:
    points = [pt(a * 30, slave=s, interval=0.05) for s in (1, 2, 3) for a in range(2)]
    # (a cap of 30 s, not the default 1 s, so that the doubling shows above the floor)
    sched = BusScheduler(
        "b", points, WIRE, share=0.05, offline_after=3, backoff=0.5, max_backoff=30.0
    )
    bus = FakeBus(sched)
    if dead:
        bus.dead.add(2)
    bus.run(until)
    return bus, sched


def test_dead_slave_backoff_and_share_of_the_bus() -> None:
    bus, sched = alive_and_dead(True)
    states = [e for e in bus.events if isinstance(e, SlaveState)]
    assert [(e.slave, e.online) for e in states if e.slave == 2] == [(2, False)]
    assert sched.online(2) is False and sched.online(1) is True
    attempts = [(s, e) for r, s, e, _ in bus.done if r.slave == 2]
    offline_at = attempts[2][1]
    probes = [(s, e) for r, s, e, _ in bus.done if r.slave == 2 and r.kind == "probe"]
    assert len(attempts) == 3 + len(probes)
    # probes are one short request each
    assert all(r.count == 1 for r, *_ in bus.done if r.kind == "probe")
    # exponential back-off: the gaps between probes grow (doubling up to the maximum)
    gaps = [b[0] - a[1] for a, b in itertools.pairwise(probes)]
    assert all(b >= a - 1e-9 for a, b in itertools.pairwise(gaps))
    assert gaps[-1] >= 4 * gaps[0]
    # the probes take at most 5 % of the bus time after the slave went offline
    spent = sum(e - s for s, e in probes)
    assert spent <= 0.05 * (bus.now - offline_at)
    # the others keep their rate: 0.05 s intervals over 120 s
    alive, _ = alive_and_dead(False)
    for slave in (1, 3):
        n_dead, n_alive = sum(bus.polls(slave).values()), sum(alive.polls(slave).values())
        assert n_dead >= 0.99 * n_alive, (slave, n_dead, n_alive)


def test_slave_comes_back_online() -> None:
    points = [pt(0, interval=0.1), pt(0, slave=2, interval=0.1)]
    sched = BusScheduler("b", points, WIRE, backoff=0.2, max_backoff=1.0)
    bus = FakeBus(sched)
    bus.dead.add(2)
    bus.run(5.0)
    bus.dead.clear()
    bus.run(10.0)
    states = [(e.slave, e.online) for e in bus.events if isinstance(e, SlaveState)]
    assert states == [(1, True), (2, False), (2, True)]
    back = next(
        e.time for e in bus.events if isinstance(e, SlaveState) and e.online and e.slave == 2
    )
    # probed within the back-off cap plus the 5 % share floor of a 100 ms timeout
    assert back <= 5.0 + max(1.0, TIMEOUT * 19) + 0.2
    late = [k for r, s, _, k in bus.done if r.slave == 2 and s > back]
    assert len(late) >= int((10.0 - back) / 0.1) - 1 and all(k == "ok" for k in late)


def test_frame_errors_count_toward_offline_but_exceptions_do_not() -> None:
    sched = BusScheduler("b", [pt(0, interval=0.1)], WIRE, offline_after=2)
    events: list[Event] = []
    t = 0.0
    for err in (FrameError("bad crc"), ExceptionResponseError(1, 3, 4), FrameError("bad")):
        req = sched.next_request(t)
        assert req is not None
        t += 0.05
        events += sched.on_failure(req, err, t)
        t = sched.deadline() or t
    assert sched.online(1) is True  # the exception in between reset the count
    st = sched.slave_stats()[1]
    assert (st.frame_errors, st.exceptions, st.requests, st.responses) == (2, 1, 3, 0)


def test_figures_latency_success_rate_and_reset() -> None:
    sched = BusScheduler("b", [pt(0, interval=0.1), pt(0, slave=2, interval=0.1)], WIRE)
    bus = FakeBus(sched)
    bus.run(2.0)
    st = sched.slave_stats()[1]
    assert st.success_rate == 1.0 and st.requests >= 20
    expect = WIRE.read("holding", 1)
    # slave 1 is asked on a quiet line (no t3.5 to wait), slave 2 right after it
    first = expect - WIRE.t35
    assert st.latency(50) == pytest.approx(first) and st.latency(99) == pytest.approx(first)
    assert sched.slave_stats()[2].latency(50) == pytest.approx(expect)
    d = st.as_dict()
    assert d["state"] == "online" and d["latency_p50_ms"] == pytest.approx(first * 1e3, abs=1e-3)
    # the wire time of each slave: its transactions with their t3.5 silences (but
    # the first, which had no frame before it)
    assert st.busy == pytest.approx((st.requests - 1) * expect + first)
    r = sched.report(bus.now)
    assert r.utilisation == pytest.approx(2 * expect / 0.1, rel=0.05)
    sched.reset_stats(bus.now)
    assert sched.slave_stats()[1].requests == 0 and sched.slave_stats()[1].online is True
    # measured turnaround: answers slower than the model raise the slave's cost
    req = sched.next_request(10.0)
    assert req is not None
    sched.on_response(req, [0], 10.0 + expect + 0.02)
    assert sched.load() > 2 * expect / 0.1


def test_tracker_change_only_and_age() -> None:
    p = pt(0, deadband=2)
    tr = Tracker()
    assert tr.offer(Update(p, 10, 1.0), 1.0)
    assert not tr.offer(Update(p, 11, 2.0), 2.0)
    assert tr.offer(Update(p, 13, 3.0), 3.0)
    assert tr.age(p.name, 3.5) == pytest.approx(0.5) and tr.age("other", 1) is None
    assert tr.latest()[p.name].value == 13


def test_scheduler_rejects_bad_setup() -> None:
    with pytest.raises(ValueError, match="share"):
        BusScheduler("b", [pt(0)], WIRE, share=0)
    with pytest.raises(ValueError, match="offline_after"):
        BusScheduler("b", [pt(0)], WIRE, offline_after=0)
    with pytest.raises(ValueError, match="on bus"):
        BusScheduler("x", [pt(0)], WIRE)
    with pytest.raises(ValueError, match="at most 1 per request"):
        BusScheduler("b", [pt(0, type="uint32")], WIRE, {1: Limits(max_registers=1)})


def test_utilisation_counts_only_the_window() -> None:
    sched = BusScheduler("b", [pt(0, interval=0.01)], WIRE)
    req = sched.next_request(0.0)
    assert req is not None
    sched.reset_stats(0.005)  # the statistics start with a transaction in flight
    sched.on_response(req, [0], 0.010)
    assert sched.slave_stats()[1].busy == pytest.approx(0.005)
    req = sched.next_request(0.0105)  # 0.5 ms after the last frame: part of t3.5
    assert req is not None
    sched.on_response(req, [0], 0.020)
    assert sched.slave_stats()[1].busy == pytest.approx(0.005 + 0.0005 + 0.0095)
    assert sched.report(0.020).utilisation == pytest.approx(1.0)
    req = sched.next_request(0.030)  # after a long silence: a whole t3.5 more
    assert req is not None
    sched.on_response(req, [0], 0.035)
    assert sched.slave_stats()[1].busy == pytest.approx(0.015 + WIRE.t35 + 0.005)


def test_a_failed_port_is_not_the_slaves_fault() -> None:
    """`on_port_failure`: nothing counts against the slave (no timeout, no failure
    towards offline_after), the block keeps its place, a probe is due again, and
    writes and reads queued meanwhile can be taken out to fail them."""
    sched = BusScheduler("b", [pt(0), pt(1)], WIRE, offline_after=2, now=0.0)
    for i in range(10):  # a port down for ten cycles: more than offline_after
        req = sched.next_request(float(i))
        assert req is not None and req.kind == "poll" and (req.address, req.count) == (0, 2)
        sched.on_port_failure(req)
    st = sched.slave_stats()[1]
    assert (st.requests, st.timeouts, st.online) == (0, 0, None)
    assert sched.deadline() == 10.0  # still on its beat
    req = sched.next_request(10.0)
    assert req is not None
    events = sched.on_response(req, [7, 8], 10.01)
    assert [type(e) for e in events] == [SlaveState, Update, Update]
    # an offline slave's probe that meets a failed port is due again at once
    for t in (11.0, 12.0):
        req = sched.next_request(t)
        assert req is not None
        sched.on_failure(req, NoResponseError("no answer", 1, 3), t + TIMEOUT)
    assert sched.online(1) is False
    probe_at = sched.deadline()
    assert probe_at is not None
    probe = sched.next_request(probe_at)
    assert probe is not None and probe.kind == "probe"
    assert sched.deadline() is None  # the probe is out
    sched.on_port_failure(probe)
    assert sched.deadline() == probe_at and sched.slave_stats()[1].timeouts == 2
    write = sched.submit_write(1, "holding", 0, [5])
    reads = sched.submit_read(1, "holding", 0, 2)
    assert sched.take_urgent() == [write, *reads]
    nxt = sched.next_request(probe_at)  # the queue is empty again: the probe is next
    assert nxt is not None and nxt.kind == "probe"


def test_offline_after_back_to_back_failures() -> None:
    """After a failure the slave's next block goes next (a confirmation): a slave
    that dies is offline ``offline_after`` timeouts after its first unanswered
    request, not ``offline_after`` turns of the schedule apart; the others are
    delayed once by at most those timeouts, and a dead slave costs the bus no more
    transactions than before it went offline."""
    # eight slaves, a block each, every 0.2 s: half the wire
    points = [pt(a, slave=s, interval=0.2) for s in range(1, 9) for a in range(3)]
    sched = BusScheduler("b", points, WIRE, offline_after=2, backoff=0.5)
    bus = FakeBus(sched)
    bus.run(1.0)
    bus.dead.add(8)
    bus.run(3.0)
    failed = [(r, s, e) for r, s, e, k in bus.done if k != "ok"]
    first_start = failed[0][1]
    off = next(e for e in bus.events if isinstance(e, SlaveState) and not e.online)
    assert off.slave == 8
    # back to back: the two failures are consecutive transactions on the bus, and
    # offline comes offline_after timeouts (plus a t3.5 each) after the first began
    i = next(k for k, d in enumerate(bus.done) if d[3] != "ok")
    assert [d[0].slave for d in bus.done[i : i + 2]] == [8, 8]
    assert [d[3] for d in bus.done[i : i + 2]] == ["NoResponseError"] * 2
    assert off.time - first_start <= 2 * (TIMEOUT + WIRE.t35) + 1e-9
    # before the confirmation, the same slave's failures were a cycle apart
    assert bus.done[i + 1][1] - bus.done[i][2] <= WIRE.t35 + 1e-9
    # the others: every block still read at its interval, late at most once by
    # the two timeouts
    for s in range(1, 8):
        starts = sorted(st for r, st, _, k in bus.done if r.slave == s and r.address == 0)
        gaps = [b - a for a, b in itertools.pairwise(starts) if a > 1.0]
        assert max(gaps) <= 0.2 + 2 * (TIMEOUT + WIRE.t35) + 1e-9
        assert sum(g > 0.2 + 0.01 for g in gaps) <= 1


def test_a_confirmed_transient_failure_keeps_the_slave_online() -> None:
    """One unanswered request: the confirmation answers, the slave stays online and
    its blocks keep their beat."""
    sched = BusScheduler("b", [pt(0, interval=0.1), pt(0, slave=2, interval=0.1)], WIRE,
                         offline_after=2)  # fmt: skip
    req = sched.next_request(0.0)
    assert req is not None and req.slave == 1
    sched.on_failure(req, NoResponseError("no answer", 1, 3), TIMEOUT)
    assert sched.deadline() == float("-inf")  # the confirmation is due at once
    conf = sched.next_request(TIMEOUT)
    assert conf is not None and (conf.slave, conf.kind) == (1, "poll")
    events = sched.on_response(conf, [5], TIMEOUT + 0.01)
    assert not any(isinstance(e, SlaveState) and not e.online for e in events)
    assert sched.online(1) is True
    nxt = sched.next_request(TIMEOUT + 0.01)
    assert nxt is not None and nxt.slave == 2  # slave 2 was due: no second confirmation
    sched.on_response(nxt, [0], TIMEOUT + 0.02)
    # neither block is issued twice in a row from stale heap entries
    seen = []
    t = 0.2
    while t < 1.0:
        r = sched.next_request(t)
        if r is None:
            t = max(t + 1e-6, sched.deadline() or t)
            continue
        seen.append((r.slave, round(t, 3)))
        t += 0.01
        sched.on_response(r, [0], t)
    # slave 1 read every 0.1 s from 0.2 on, once each (its beat restarted by the
    # confirmation at 0.1); slave 2 caught up from 0.1
    ones = [t for s, t in seen if s == 1]
    assert len(ones) >= 8 and all(b - a >= 0.08 for a, b in itertools.pairwise(ones))


# ---------------------------------------------------------------------- the silence timer

#: a request's wait before its answer can begin: the t3.5 silence and 8 bytes on the wire
SEND = WIRE.t35 + 8 * WIRE.char
#: the master's pause after a failed transaction (pyrtu's settle: a late answer may come)
SETTLE = 0.02


def _silent_bus(offline_after: int = 2, **kw: object) -> BusScheduler:
    points = [pt(0, interval=0.05), pt(0, slave=2, interval=0.05)]
    return BusScheduler("b", points, WIRE, offline_after=offline_after,  # type: ignore[arg-type]
                        timeout=TIMEOUT, **kw)  # fmt: skip


def _fail(sched: BusScheduler, req: ScheduledRequest, at: float) -> list[Event]:
    return sched.on_failure(req, NoResponseError("no answer", req.slave, 3), at)


def _next_for(sched: BusScheduler, slave: int, t: float) -> tuple[ScheduledRequest, float]:
    """The requests from ``t`` on, every other slave's answered 3 ms later, until one
    for ``slave``: that request and its time."""
    r = sched.next_request(t)
    while r is None or r.slave != slave:
        if r is not None:
            sched.on_response(r, [0], t + 0.003)
        t += 0.003
        r = sched.next_request(t)
    return r, t


def test_silent_slave_offline_offline_after_timeouts_after_its_first_unanswered_request() -> None:
    """Asked twice back to back and silent for offline_after x timeout from the end
    of its first unanswered request: offline then, while the second request still
    waits (each failed transaction costs the t3.5, the request, the timeout and the
    master's settling pause, so waiting for the second's own timeout came later)."""
    sched = _silent_bus()
    t0 = 1.0
    req = sched.next_request(t0)
    assert req is not None and req.slave == 1
    assert sched.offline_due(req) is None  # nothing unanswered yet
    end1 = t0 + SEND  # the request's last byte: its timeout starts here
    assert _fail(sched, req, end1 + TIMEOUT) == []
    conf = sched.next_request(end1 + TIMEOUT)
    assert conf is not None and (conf.slave, conf.kind) == (1, "poll")
    due = sched.offline_due(conf)
    assert due == pytest.approx(end1 + 2 * TIMEOUT)
    # the second request goes out after the settling pause: its own timeout would
    # end later than the bound
    assert end1 + TIMEOUT + SETTLE + SEND + TIMEOUT > due
    assert sched.on_silence(conf, due - 1e-6) == []  # not yet
    (off,) = sched.on_silence(conf, due)
    assert isinstance(off, SlaveState) and (off.slave, off.online) == (1, False)
    assert off.time == due
    assert sched.online(1) is False
    assert sched.on_silence(conf, due + 0.01) == []  # once
    # the request in flight then fails: nothing more, and the first probe keeps
    # the initial back-off (not doubled), counted from that failure as before
    end2 = end1 + TIMEOUT + SETTLE + SEND + TIMEOUT
    assert _fail(sched, conf, end2) == []
    busy2 = end2 - (end1 + TIMEOUT)  # the second transaction's wire time
    t, probes = due + 0.01, []
    while t < due + 3.0:
        r = sched.next_request(t)
        if r is None:
            t = max(t + 1e-4, sched.deadline() or t)
            continue
        assert r.slave == 2 or r.kind == "probe"  # slave 1's blocks left the schedule
        if r.kind == "probe":
            probes.append(t)
            _fail(sched, r, t + SEND + TIMEOUT)
            t += SEND + TIMEOUT
        else:
            sched.on_response(r, [0], t + 0.003)
            t += 0.003
    # the first probe after the back-off counted from the second failure (as when
    # that failure took it offline: never less than share keeps), not doubled
    assert probes[0] == pytest.approx(end2 + max(0.5, busy2 * (1 / 0.05 - 1)), abs=0.005)


def test_a_late_answer_brings_the_slave_back_at_once() -> None:
    """Offline by the timer, then the request in flight is answered (within its own
    timeout): back online at once, its values delivered, its blocks due at once."""
    sched = _silent_bus()
    req = sched.next_request(0.0)
    assert req is not None
    _fail(sched, req, SEND + TIMEOUT)
    conf = sched.next_request(SEND + TIMEOUT)
    assert conf is not None
    due = sched.offline_due(conf)
    assert due is not None
    sched.on_silence(conf, due)
    events = sched.on_response(conf, [7], due + 0.005)
    back = [e for e in events if isinstance(e, SlaveState)]
    assert [(e.slave, e.online) for e in back] == [(1, True)]
    assert [e.value for e in events if isinstance(e, Update)] == [7]
    assert sched.online(1) is True
    assert sched.offline_due(conf) is None
    nxt = sched.next_request(due + 0.005)
    assert nxt is not None and nxt.slave in (1, 2)
    kinds = {(nxt.slave, nxt.kind)}
    sched.on_response(nxt, [0], due + 0.008)
    nxt2 = sched.next_request(due + 0.008)
    assert nxt2 is not None
    kinds.add((nxt2.slave, nxt2.kind))
    assert (1, "poll") in kinds  # slave 1's block is due at once, no probe


def test_a_slave_that_answers_within_its_timeout_is_never_offline() -> None:
    """Slow answers (just within the timeout) never arm the timer; one unanswered
    request followed by an answer disarms it; the next silence starts afresh."""
    sched = _silent_bus()
    t = 0.0
    for _ in range(50):
        r = sched.next_request(t)
        if r is None:
            t = max(t + 1e-4, sched.deadline() or t)
            continue
        assert sched.offline_due(r) is None
        t += SEND + TIMEOUT * 0.99
        events = sched.on_response(r, [0], t)
        assert not any(isinstance(e, SlaveState) and not e.online for e in events)
    assert sched.online(1) is True and sched.online(2) is True
    # one unanswered, the confirmation answers: nothing armed afterwards
    r, t = _next_for(sched, 1, t)
    _fail(sched, r, t + SEND + TIMEOUT)
    t += SEND + TIMEOUT
    conf = sched.next_request(t)
    assert conf is not None and conf.slave == 1 and sched.offline_due(conf) is not None
    sched.on_response(conf, [0], t + 0.003)
    t += 0.003
    assert sched.on_silence(conf, t + 1.0) == []  # answered: the timer is disarmed
    assert sched.online(1) is True
    # a new silence counts from its own first unanswered request
    r, t = _next_for(sched, 1, t)
    _fail(sched, r, t + SEND + TIMEOUT)
    conf = sched.next_request(t + SEND + TIMEOUT)
    assert conf is not None
    assert sched.offline_due(conf) == pytest.approx(t + SEND + 2 * TIMEOUT)


def test_the_silence_timer_needs_back_to_back_silent_failures() -> None:
    """No timer: without a timeout, with offline_after 1 (the first failure is the
    offline one), after a garbled answer (the slave is not silent), or when another
    transaction came between the failure and the next request (a queued write goes
    first): then the last request gets its whole timeout, as before."""
    plain = BusScheduler("b", [pt(0)], WIRE, offline_after=2)
    r = plain.next_request(0.0)
    assert r is not None
    _fail(plain, r, 0.1)
    conf = plain.next_request(0.1)
    assert conf is not None and plain.offline_due(conf) is None

    one = _silent_bus(offline_after=1)
    r = one.next_request(0.0)
    assert r is not None and one.offline_due(r) is None
    assert any(isinstance(e, SlaveState) for e in _fail(one, r, SEND + TIMEOUT))

    garbled = _silent_bus()
    r = garbled.next_request(0.0)
    assert r is not None
    garbled.on_failure(r, FrameError("bad crc", 1, 3), 0.01)
    conf = garbled.next_request(0.01)
    assert conf is not None and conf.slave == 1 and garbled.offline_due(conf) is None

    between = _silent_bus()
    r = between.next_request(0.0)
    assert r is not None
    _fail(between, r, SEND + TIMEOUT)
    w = between.submit_write(2, "holding", 0, [1])
    assert between.next_request(SEND + TIMEOUT) is w
    between.on_response(w, None, SEND + TIMEOUT + 0.005)
    conf = between.next_request(SEND + TIMEOUT + 0.005)
    assert conf is not None and conf.slave == 1
    assert between.offline_due(conf) is None
    # its failure then takes the slave offline by the count, as without a timer
    assert any(isinstance(e, SlaveState) for e in _fail(between, conf, 0.3))


def test_offline_after_three_arms_on_the_third_request() -> None:
    sched = _silent_bus(offline_after=3)
    r = sched.next_request(0.0)
    assert r is not None
    _fail(sched, r, SEND + TIMEOUT)
    second = sched.next_request(SEND + TIMEOUT)
    assert second is not None and sched.offline_due(second) is None
    end2 = SEND + TIMEOUT + SETTLE + SEND + TIMEOUT
    _fail(sched, second, end2)
    third = sched.next_request(end2)
    assert third is not None and third.slave == 1
    assert sched.offline_due(third) == pytest.approx(SEND + 3 * TIMEOUT)


def test_timeout_is_checked() -> None:
    for bad in (0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="timeout"):
            BusScheduler("b", [pt(0)], WIRE, timeout=bad)


# ---------------------------------------------------------------------- through the driver


@pytest.mark.wall_clock
def test_the_poller_arms_the_silence_timer_on_the_virtual_bus() -> None:
    """The real driver on the virtual bus: a CFW701 at 1 answers, nobody answers at
    7.  Slave 7 goes offline while its second request still waits (before that
    request's failure is reported: the master pauses ``settle``, 20 ms, after the
    first failure, so the second failure comes at least that much after the
    timer's time), never before 2 x timeout after the end of the first (its
    failure's report minus the timeout); the second failure adds no event."""
    import asyncio

    from pyrtu.devices import CFW701Simulator
    from pyrtu.poller import Bus, Poller, make_config

    vbus = pytest.importorskip("pyrtu.vbus")
    timeout = 0.1
    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=115200, parity="N")
        try:
            master = {"baudrate": 115200, "parity": "N", "timeout": timeout}
            line = Bus("line", bus.paths[0], master, offline_after=2, backoff=5.0, max_backoff=5.0)
            points = [Point("a", "line", 1, "holding", 0, interval=0.02),
                      Point("b", "line", 7, "holding", 0, interval=0.02)]  # fmt: skip
            poller = Poller(make_config([line], points), changes_only=False)
            sched = poller.scheduler("line")
            failures: list[float] = []
            offline: list[tuple[float, int]] = []
            second: list[SlaveState] = []  # events of the second failure
            real = sched.on_failure

            def failed(req: ScheduledRequest, error: BaseException, now: float) -> list[Event]:
                if req.slave == 7:
                    failures.append(now)
                events = real(req, error, now)
                if req.slave == 7 and len(failures) == 2:
                    second.extend(e for e in events if isinstance(e, SlaveState))
                return events

            sched.on_failure = failed  # type: ignore[method-assign]

            def on_event(ev: Event) -> None:
                if isinstance(ev, SlaveState) and ev.slave == 7 and not ev.online:
                    offline.append((ev.time - sched.stamp_offset, len(failures)))

            poller.on_event(on_event)

            async def main() -> None:
                async with poller:
                    give_up = time.monotonic() + 30
                    while len(failures) < 2 or not offline:
                        assert time.monotonic() < give_up, "slave 7 never went offline"
                        await asyncio.sleep(0.01)

            asyncio.run(main())
        finally:
            sim.close()
    (at, failed_before), *_ = offline
    assert failed_before == 1 and second == [], "offline only when the second failure ended"
    assert at >= failures[0] - timeout + 2 * timeout - 1e-6
    assert at < failures[1]


# -- a gateway's "no device answered" (#27.3), a returning slave found soon (#27.7) --


@pytest.mark.parametrize(
    ("code", "silent"), [(9, False), (10, True), (11, True), (12, False), (4, False)]
)
def test_no_device_answered_is_exactly_0x0a_and_0x0b(code: int, silent: bool) -> None:
    # Application Protocol V1.1b section 7: 0x0A gateway path unavailable, 0x0B gateway
    # target device failed to respond; their neighbours are answers of the device
    assert ExceptionResponseError(1, 3, code).no_device_answered is silent


class GatewayBus(FakeBus):
    """A bus behind a Modbus TCP gateway: a dead slave is answered by the gateway with
    exception ``code`` after the gateway's own timeout."""

    code = 11

    def answer(self, req: ScheduledRequest) -> tuple[Outcome, float]:
        if req.slave in self.dead:
            return ExceptionResponseError(req.slave, req.function, self.code), TIMEOUT
        return super().answer(req)


@pytest.mark.parametrize("code", [10, 11])
def test_a_gateways_no_answer_takes_the_slave_offline_and_back(code: int) -> None:
    points = [pt(0, interval=0.1), pt(0, slave=2, interval=0.1)]
    sched = BusScheduler("b", points, WIRE, offline_after=3)
    bus = GatewayBus(sched)
    bus.code = code
    bus.run(1.0)
    bus.dead.add(2)
    bus.run(5.0)
    states = [(e.slave, e.online) for e in bus.events if isinstance(e, SlaveState)]
    assert states == [(1, True), (2, True), (2, False)]
    st = sched.slave_stats()[2]
    # counted as what they are: no answer of the slave, not its exceptions
    assert st.exceptions == 0 and st.timeouts >= 3
    assert sched.online(1) is True
    bus.dead.clear()
    bus.run(10.0)
    states = [(e.slave, e.online) for e in bus.events if isinstance(e, SlaveState)]
    assert states[-1] == (2, True)


@pytest.mark.parametrize("alone", [True, False])
def test_a_slave_back_after_a_long_outage_is_found_within_a_second(alone: bool) -> None:
    """A minute's outage: the probes' back-off stops at 1 s (docs/POLLER.md), so the
    returning slave is probed within 1 s (or, while another slave is online, within
    the 5 % share floor of its 100 ms timeout: 19 x 0.1 s) plus one probe."""
    points = [pt(0, slave=2, interval=0.1)]
    if not alone:
        points.append(pt(0, interval=0.1))
    sched = BusScheduler("b", points, WIRE)
    bus = FakeBus(sched)
    bus.dead.add(2)
    bus.run(60.0)
    bus.dead.clear()
    bus.run(70.0)
    back = next(
        e.time for e in bus.events if isinstance(e, SlaveState) and e.online and e.slave == 2
    )
    gap = 1.0 if alone else max(1.0, TIMEOUT * (1 / 0.05 - 1))
    assert back <= 60.0 + gap + TIMEOUT + 1e-6
    probes = [(s, e) for r, s, e, _ in bus.done if r.slave == 2 and r.kind == "probe"]
    # and the outage stays cheap: one short request per gap, never more often
    assert all(r.count == 1 for r, *_ in bus.done if r.kind == "probe")
    starts = [s for s, _ in probes]
    assert min(b - a for a, b in itertools.pairwise(starts)) >= 0.5 + TIMEOUT - 1e-6
    if not alone:  # within the share while another slave is polled
        spent = sum(e - s for s, e in probes)
        assert spent <= 0.05 * 60.0


def test_a_tcp_bus_is_priced_by_its_round_trip() -> None:
    """10,000 registers at 1 s on a tcp:// bus: 80 reads of 125 registers (the spec's
    maximum), each costing the assumed 2 ms round trip (docs/POLLER.md) until it is
    measured: load 80 x 0.002 = 0.16, not the 12 of a 19200-baud line; once a
    transaction's round trip is measured (1 ms here), the load is 80 x 0.001."""
    from pyrtu.poller import Bus

    bus = Bus("b", "tcp://127.0.0.1:502")
    points = [pt(a) for a in range(10_000)]
    sched = BusScheduler("b", points, bus.wire())
    assert len(sched.blocks) == 80
    assert sched.load() == pytest.approx(80 * 0.002 / 1.0)
    t = 0.0
    while (req := sched.next_request(t)) is not None:
        t += 0.001
        sched.on_response(req, [0] * req.count, t)
    assert sched.load() == pytest.approx(80 * 0.001 / 1.0)
    assert sched.report(1.0).utilisation == pytest.approx(0.08)
    # a serial bus is still priced by its line (the 19200-baud default: 11 bits a
    # character, 255 characters a response of 125 registers)
    serial = BusScheduler("b", points, Bus("b", "/dev/ttyUSB0").wire())
    assert serial.load() > 80 * 255 * 11 / 19200
