"""The bus scheduler at its edges, driven by hand on a fake clock: the settings at
their bounds, the beat of a block issued late or early, the probes' back-off
doubling to its cap, the requests' wire cost from the spec's frame sizes, the load
computed every 16 transactions.  Expected values come from the spec (Application
Protocol V1.1b 6.5, 6.6, 6.11, 6.12: the write frames), docs/POLLER.md and hand
arithmetic, never from the scheduler."""

from __future__ import annotations

import itertools
import math

import pytest

from pyrtu.pdu.errors import NoResponseError
from pyrtu.poller import BusScheduler, Point, ScheduledRequest, SlaveState, Wire

#: 1 ms a character, t3.5 of 4 ms, no turnaround: round figures
WIRE = Wire(0.001, 0.004)


def pt(address: int, name: str | None = None, **kw: object) -> Point:
    fields: dict[str, object] = dict(bus="b", slave=1, table="holding", interval=1.0)
    fields.update(kw)
    return Point(name or f"s{fields['slave']}.{address}", address=address, **fields)  # type: ignore[arg-type]


def silent(req: ScheduledRequest) -> NoResponseError:
    return NoResponseError("no answer", req.slave, req.function)


def take(sched: BusScheduler, now: float) -> ScheduledRequest:
    req = sched.next_request(now)
    assert req is not None, now
    return req


# -- settings ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kw", "ok"),
    [
        ({"share": 1}, True),
        ({"share": 1e-9}, True),
        ({"share": 0}, False),
        ({"share": 1.000001}, False),
        ({"share": -0.5}, False),
        ({"offline_after": 1}, True),
        ({"offline_after": 0}, False),
        ({"offline_after": True}, False),
        ({"offline_after": 2.0}, False),
        ({"backoff": 1.0, "max_backoff": 1.0}, True),
        ({"backoff": 1e-9}, True),
        ({"backoff": 0.0}, False),
        ({"backoff": -0.5}, False),
        ({"backoff": 1.5, "max_backoff": 1.0}, False),
        ({"timeout": 1e-9}, True),
        ({"timeout": None}, True),
        ({"timeout": 0.0}, False),
        ({"timeout": -1.0}, False),
    ],
)
def test_settings_are_checked_at_their_bounds(kw: dict[str, object], ok: bool) -> None:
    name = next(iter(kw))
    if ok:
        BusScheduler("b", [pt(0)], WIRE, **kw)  # type: ignore[arg-type]
    else:
        with pytest.raises(ValueError, match=f"^{name} must be"):
            BusScheduler("b", [pt(0)], WIRE, **kw)  # type: ignore[arg-type]


# -- the beat ------------------------------------------------------------------------------


def test_a_late_block_keeps_its_beat_unless_a_whole_interval_is_missed() -> None:
    """Due at 0, 1, 2, ...: issued late, the next is still due on the beat; issued
    more than an interval after the next beat, the beat starts again from then."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.125)
    assert sched.deadline() == 1.0
    req = take(sched, 1.5)  # half an interval late: next due on the beat, at 2
    sched.on_response(req, [0], 1.625)
    assert sched.deadline() == 2.0
    req = take(sched, 4.0)  # due 2, the next beat 3: 3 + 1 is not before 4: due 3
    sched.on_response(req, [0], 4.125)
    assert sched.deadline() == 3.0
    req = take(sched, 4.25)  # due 3, the next beat 4: 4 + 1 is not before 4.25: due 4
    sched.on_response(req, [0], 4.375)
    assert sched.deadline() == 4.0
    req = take(sched, 5.5)  # due 4, the next 5: 5 + 1 < 5.5? no: due 5
    sched.on_response(req, [0], 5.625)
    assert sched.deadline() == 5.0
    req = take(sched, 7.0)  # due 5, next 6, 6 + 1 is not before 7: due 6
    sched.on_response(req, [0], 7.125)
    req = take(sched, 8.5)  # due 6, next 7, 7 + 1 < 8.5: a beat missed, due now
    sched.on_response(req, [0], 8.625)
    assert sched.deadline() == 8.5


def test_a_confirmation_ahead_of_its_time_restarts_the_beat() -> None:
    # two blocks of slave 1 (far apart); the first fails; the second, due at 0.75,
    # is asked at once (0.5) to confirm, and is then next due an interval after that
    sched = BusScheduler("b", [pt(0), pt(500, interval=0.75)], WIRE)
    first, second = take(sched, 0.0), take(sched, 0.0)
    assert (first.address, second.address) == (0, 500)
    sched.on_response(second, [0], 0.25)
    sched.on_failure(first, silent(first), 0.5)
    confirm = take(sched, 0.5)
    assert confirm.address == 500 and confirm.kind == "poll"
    sched.on_response(confirm, [0], 0.625)
    # the first is due on its beat at 1; the confirmed one restarted at 0.5: 1.25
    req = take(sched, 1.0)
    assert req.address == 0
    sched.on_response(req, [0], 1.125)
    assert sched.deadline() == 1.25


def test_a_block_in_flight_as_a_confirmation_is_not_issued_again() -> None:
    """The confirmation takes the slave's earliest-due block out of its turn: while
    it is in flight its place in the heap is stale, whatever the order."""
    sched = BusScheduler("b", [pt(0), pt(500)], WIRE)
    write = sched.submit_write(1, "holding", 7, [1])
    assert take(sched, 0.0) is write
    sched.on_failure(write, silent(write), 0.25)
    confirm = take(sched, 0.25)  # the earliest due of slave 1: the block at 0
    assert confirm.address == 0
    nxt = take(sched, 0.25)  # the block at 0 is in flight: the other one
    assert nxt.address == 500
    assert sched.next_request(0.25) is None
    # and the other way round: the block at 500 confirmed while the one at 0 waits
    sched = BusScheduler("b", [pt(0), pt(500)], WIRE)
    first = take(sched, 0.0)
    sched.on_failure(first, silent(first), 0.25)
    confirm = take(sched, 0.25)
    assert confirm.address == 500
    assert sched.next_request(0.5) is None  # 0 is due at 1, 500 is in flight
    assert sched.deadline() == 1.0


def test_a_failed_write_to_a_slave_without_points_confirms_nothing() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    write = sched.submit_write(9, "holding", 0, [1])
    assert take(sched, 0.0) is write
    sched.on_failure(write, silent(write), 0.25)
    poll = take(sched, 0.25)
    assert (poll.kind, poll.slave, poll.address) == ("poll", 1, 0)


# -- health --------------------------------------------------------------------------------


def probe_starts(sched: BusScheduler, until: float) -> list[float]:
    """Drive a lone slave that never answers: each request takes 0.125 s."""
    now, starts = 0.0, []
    while now < until:
        req = sched.next_request(now)
        if req is None:
            deadline = sched.deadline()
            assert deadline is not None and deadline > now
            now = deadline
            continue
        if req.kind == "probe":
            starts.append(now)
        now += 0.125
        sched.on_failure(req, silent(req), now)
    return starts


def test_the_back_off_doubles_from_backoff_to_max_backoff() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1, backoff=0.25, max_backoff=4.0)
    starts = probe_starts(sched, 30.0)
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    # offline at 0.125; a probe after 0.25, then each failed probe doubles the wait
    assert starts[0] == 0.125 + 0.25
    assert gaps[:6] == [0.125 + w for w in (0.5, 1.0, 2.0, 4.0, 4.0, 4.0)]


def test_the_default_back_off_is_half_a_second_then_one() -> None:
    """docs/POLLER.md: the back-off doubles from 0.5 s to 1 s (a slave that comes
    back is found within about a second)."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1)
    starts = probe_starts(sched, 10.0)
    assert starts[0] == 0.125 + 0.5
    assert [b - a for a, b in itertools.pairwise(starts)][:3] == [1.125] * 3


def test_the_probe_asks_the_smallest_point_of_the_slave() -> None:
    """One short request: the slave's narrowest point (then the lowest address),
    whatever its table."""
    points = [pt(0, "wide", type="uint32"), pt(5, "coil", table="coils")]
    sched = BusScheduler("b", points, WIRE, offline_after=1)
    now = 0.0
    while True:
        req = take(sched, now)
        now += 0.125
        if req.kind == "probe":
            break
        sched.on_failure(req, silent(req), now)
        deadline = sched.deadline()
        now = max(now, deadline if deadline is not None else now)
    assert (req.table, req.address, req.count, req.function) == ("coils", 5, 1, 1)
    # t3.5, the 8-byte request, the answer: slave, function, count, 1 byte, CRC
    assert req.cost == pytest.approx(0.004 + 8 * 0.001 + 6 * 0.001)


def test_a_slave_without_points_is_probed_with_holding_register_0() -> None:
    """docs/POLLER.md: a slave known only from writes and on-demand reads has no
    point to probe with: one holding register at address 0 (any answer, exception
    responses included, brings it back)."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1)
    write = sched.submit_write(9, "holding", 7, [1])
    assert take(sched, 0.0) is write
    (state,) = sched.on_failure(write, silent(write), 0.125)
    assert isinstance(state, SlaveState) and (state.slave, state.online) == (9, False)
    now = 0.125
    while True:
        req = take(sched, now)
        if req.kind == "probe":
            break
        now += 0.125
        sched.on_response(req, [0], now)
        deadline = sched.deadline()
        now = max(now, deadline if deadline is not None else now)
    assert (req.slave, req.table, req.address, req.count, req.function) == (9, "holding", 0, 1, 3)


def test_a_requests_repr_shows_its_fields_not_the_schedulers_task() -> None:
    """A poll carries the scheduler's private task (its due time, its place in the
    heap): a log line printing the request shows what goes on the wire, not that."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    poll = take(sched, 0.0)
    assert poll.task is not None
    text = repr(poll)
    assert text.startswith("ScheduledRequest(kind='poll', slave=1, table='holding', address=0,")
    assert "task" not in text and "_Task" not in text


# -- costs and figures ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("table", "values", "request_bytes"),
    [
        # FC 05 / 06: slave, function, address 2, value 2, CRC 2
        ("coils", [True], 8),
        ("holding", [7], 8),
        # FC 15: slave, function, address 2, quantity 2, byte count, ceil(n/8), CRC 2
        ("coils", [True] * 2, 9 + 1),
        ("coils", [True] * 9, 9 + 2),
        # FC 16: ... 2n bytes of values
        ("holding", [1, 2], 9 + 4),
        ("holding", [1] * 123, 9 + 246),
    ],
)
def test_a_write_costs_its_spec_frames(table: str, values: list[int], request_bytes: int) -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = sched.submit_write(1, table, 0, values)
    # t3.5, the request, and the 8-byte echo of address and value/quantity
    assert req.cost == pytest.approx(0.004 + request_bytes * 0.001 + 8 * 0.001)


def test_an_on_demand_read_costs_its_spec_frames() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    (req,) = sched.submit_read(1, "input", 0, 10)
    assert req.cost == pytest.approx(0.004 + 8 * 0.001 + (5 + 20) * 0.001)


def test_the_load_is_computed_every_16_transactions() -> None:
    """`last_load` (docs: every 16 transactions and on slave changes): each answer
    here moves the measured turnaround, so a stale figure shows.  The first answer
    brings the slave online (a change): computed then, and every 16th after."""
    sched = BusScheduler("b", [pt(0, interval=0.5)], WIRE)
    seen = []
    now = 0.0
    for n in range(1, 49):
        req = take(sched, now)
        now += 0.01 * n  # a longer turnaround each time
        sched.on_response(req, [0], now)
        seen.append(sched.last_load)
        now = max(now, sched.deadline() or now)
    assert seen[0] > 0.0 and seen[1:16] == [seen[0]] * 15
    assert seen[16] > seen[0] and seen[17:32] == [seen[16]] * 15
    assert seen[32] > seen[16] and seen[33:48] == [seen[32]] * 15
    assert sched.load() > seen[47]  # computed now, with the 48th answer


def test_the_report_covers_the_window_since_the_statistics_started() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    assert sched.report(5.0).seconds == 0.0 and sched.utilisation(5.0) == 0.0
    req = take(sched, 2.0)
    sched.on_response(req, [0], 2.25)
    report = sched.report(4.0)
    assert report.seconds == 2.0 and report.transactions == 1
    assert report.utilisation == pytest.approx(0.25 / 2.0)
    assert sched.report(1.0).seconds == 0.0  # a clock before the start: no window
    sched.reset_stats(3.0)
    assert sched.report(4.0).seconds == 1.0 and sched.report(4.0).transactions == 0


def test_a_slave_offline_and_back_is_reported_once_each_way() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=2)
    req = take(sched, 0.0)
    assert sched.on_failure(req, silent(req), 0.125) == []
    req = take(sched, 0.125)
    (off,) = [e for e in sched.on_failure(req, silent(req), 0.25) if isinstance(e, SlaveState)]
    assert (off.slave, off.online, off.time) == (1, False, 0.25)
    probe = take(sched, math.inf)
    (back,) = [e for e in sched.on_response(probe, [0], 1.0) if isinstance(e, SlaveState)]
    assert (back.online, back.time) == (True, 1.0)
    assert sched.deadline() == 1.0  # its blocks due at once


def test_the_measured_turnaround_prices_the_blocks() -> None:
    """The slave's turnaround is measured from each answer (the time from the
    request issued to the answer, less the frames) and smoothed, 0.9 of the old and
    0.1 of the new; a block costs its frames plus that turnaround."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    frames = 0.004 + 8 * 0.001 + 7 * 0.001  # t3.5, request, response of one register
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.025)  # busy 25 ms: a turnaround of 6 ms
    assert sched.load() == pytest.approx(frames + 0.006)
    req = take(sched, 1.0)
    sched.on_response(req, [0], 1.035)  # 35 ms: 16 ms this time
    turnaround = 0.9 * 0.006 + 0.1 * (0.035 - frames)
    assert sched.load() == pytest.approx(frames + turnaround)


@pytest.mark.parametrize("alone", [True, False])
def test_a_probe_waits_its_share_of_the_bus_while_others_are_polled(alone: bool) -> None:
    """docs/POLLER.md: the back-off, and never less than what keeps the probes within
    ``share`` of the bus time while another slave is online: a failure that held the
    bus 0.5 s with a share of 1/4 waits 0.5 x (4 - 1) = 1.5 s."""
    points = [pt(0, slave=2)] + ([] if alone else [pt(0, slave=1, interval=10.0)])
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=0.25, backoff=0.5)
    now = 0.0
    if not alone:
        req = take(sched, now)
        assert req.slave == 1
        now = 0.125
        sched.on_response(req, [0], now)
    req = take(sched, now)
    assert req.slave == 2
    sched.on_failure(req, silent(req), now + 0.5)
    assert sched.deadline() == now + 0.5 + (0.5 if alone else 1.5)


@pytest.mark.parametrize(("interval", "overloaded"), [(4.75, False), (2.375, True), (1.0, True)])
def test_the_bus_is_overloaded_only_above_a_load_of_one(interval: float, overloaded: bool) -> None:
    # 0.25 s a character, t3.5 of 1 s: a read of one register is 1 + 8 x 0.25 + 7 x 0.25
    # = 4.75 s of wire: every 4.75 s a load of exactly 1 (the wire just carries it)
    sched = BusScheduler("b", [pt(0, interval=interval)], Wire(0.25, 1.0))
    report = sched.report(0.0)
    assert report.load == 4.75 / interval
    assert report.overloaded is overloaded


def test_an_offline_slaves_blocks_leave_the_load() -> None:
    """docs/POLLER.md: offline, its blocks leave the schedule: the load is what the
    online slaves' blocks need (4.75 s of wire every 9.5 s each: 0.5)."""
    points = [pt(0, slave=1, interval=9.5), pt(0, slave=2, interval=9.5)]
    sched = BusScheduler("b", points, Wire(0.25, 1.0), offline_after=1)
    assert sched.load() == 1.0
    while (req := take(sched, 0.0)).slave != 2:
        pass
    sched.on_failure(req, silent(req), 0.0)
    assert sched.online(2) is False
    assert sched.load() == 0.5


def test_a_clock_behind_the_request_counts_no_negative_latency() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 1.0)
    sched.on_response(req, [0], 0.5)  # an answer stamped before the request: a clock step
    assert list(sched.slave_stats()[1].latencies) == [0.0]


def test_a_slave_silenced_offline_is_probed_after_the_back_off() -> None:
    """Taken offline by its silence timer (`on_silence`) while its request is still
    in flight, that request has held the bus for no counted time yet: the first
    probe waits the back-off (0.5 s), not a share floor of its wire time."""
    points = [pt(0, slave=1, interval=10.0), pt(0, slave=2, interval=10.0)]
    sched = BusScheduler("b", points, WIRE, offline_after=2, timeout=0.125)
    req = take(sched, 0.0)
    assert req.slave == 1
    sched.on_response(req, [0], 0.0625)
    first = take(sched, 0.0625)
    assert first.slave == 2
    sched.on_failure(first, silent(first), 0.1875)  # silent from 0.0625
    second = take(sched, 0.1875)  # the confirmation
    assert second.slave == 2
    due = sched.offline_due(second)
    assert due == 0.0625 + 2 * 0.125
    (off,) = sched.on_silence(second, due)
    assert isinstance(off, SlaveState) and not off.online
    assert sched.deadline() == due + 0.5


def test_polls_and_probes_carry_no_tag_and_submissions_count_from_one() -> None:
    """A tag says who waits for the outcome: 0 for the scheduler's own polls and
    probes (the driver resolves no caller for them), 1, 2, ... for the writes and
    on-demand reads submitted, so each outcome reaches its own caller."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1)
    write = sched.submit_write(1, "holding", 3, [1])
    reads = sched.submit_read(1, "holding", 0, 130)
    assert [write.tag, *(r.tag for r in reads)] == [1, 2, 3]
    for _ in range(3):
        take(sched, 0.0)
    poll = take(sched, 0.0)
    assert (poll.kind, poll.tag) == ("poll", 0)
    sched.on_failure(poll, silent(poll), 0.125)
    probe = take(sched, 10.0)
    assert (probe.kind, probe.tag) == ("probe", 0)


def test_two_identical_writes_are_two_requests() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    first = sched.submit_write(1, "holding", 3, [1])
    second = sched.submit_write(1, "holding", 3, [1])
    second.tag = first.tag  # even alike in every field
    assert first != second and len({first, second}) == 2


def test_a_block_not_yet_read_is_not_lagging() -> None:
    """Lagging: started more than one interval late last time; a block never
    issued has not started late."""
    sched = BusScheduler("b", [pt(0, interval=0.5)], WIRE)
    assert sched.lagging() == () and sched.report(0.0).lagging == ()
    req = take(sched, 0.25)  # due 0, half an interval late
    sched.on_response(req, [0], 0.3125)
    assert sched.lagging() == ()
    req = take(sched, 1.25)  # due 0.5: 0.75 late, more than the interval
    sched.on_response(req, [0], 1.3125)
    assert sched.lagging() == ("s1.0",)


def test_the_latency_percentiles_are_of_the_last_1024_and_at_most_2047_are_kept() -> None:
    """docs/POLLER.md: a slave's latency percentiles are over its last 1024 answers;
    the older go in bulk when 2048 are reached (1024 kept).  Latencies 0, 1, 2... so
    the window's nearest-rank p0 is its oldest, p100 its newest, p50 the 512th."""
    from pyrtu.poller import SlaveStats

    st = SlaveStats("b", 1)
    assert st.latency(50) is None
    for i in range(1024):
        st.note_latency(float(i))
    assert (st.latency(0), st.latency(50), st.latency(100)) == (0.0, 511.0, 1023.0)
    for i in range(1024, 2047):
        st.note_latency(float(i))
    assert len(st.latencies) == 2047  # one short of the trim: all kept
    assert (st.latency(0), st.latency(100)) == (1023.0, 2046.0)  # the last 1024
    st.note_latency(2047.0)
    assert list(st.latencies) == [float(i) for i in range(1024, 2048)]
    assert (st.latency(0), st.latency(50), st.latency(100)) == (1024.0, 1535.0, 2047.0)


# -- the steady state the tcp:// mux repeats --------------------------------------------


def test_a_repeated_block_keeps_the_beat_next_request_keeps() -> None:
    """`repeated` (the mux sent the block again by itself) moves the beat as
    `next_request` does: the dues of the late-block test above, from the same
    send times."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.125)
    assert sched.deadline() == 1.0
    for start, due in [(1.5, 2.0), (4.0, 3.0), (4.25, 4.0), (5.5, 5.0), (7.0, 6.0), (8.5, 8.5)]:
        sched.repeated(req, start)
        assert req.issued == start
        assert sched.deadline() is None  # in flight: out of the schedule
        sched.on_response(req, [0], start + 0.125)
        assert sched.deadline() == due
    st = sched.slave_stats()[1]
    assert (st.requests, st.responses) == (7, 7)
    assert list(st.latencies) == [0.125] * 7


def test_a_repeated_block_keeps_one_entry_in_the_schedule() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.125)
    for i in range(1, 200):
        sched.repeated(req, float(i))
        sched.on_response(req, [0], i + 0.125)
    assert len(sched._heap) == 1  # (each outcome's entry goes at the next repeat)
    assert take(sched, 200.0).address == 0  # and it is due on its beat


def test_a_write_or_read_is_not_repeated() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    sched.submit_write(1, "holding", 5, [1])
    write = take(sched, 0.0)
    assert not sched.steady(write)
    with pytest.raises(ValueError, match="only a poll block"):
        sched.repeated(write, 1.0)


def test_only_a_lone_block_with_nothing_waiting_is_steady() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1)
    req = take(sched, 0.0)
    assert sched.steady(req)
    sched.submit_read(1, "holding", 7, 1)  # a read queued
    assert not sched.steady(req)
    read = take(sched, 0.0)
    sched.on_response(read, [0], 0.1)
    assert sched.steady(req)
    two = BusScheduler("b", [pt(0), pt(500)], WIRE)  # two blocks
    assert not two.steady(take(two, 0.0))
    # a slave with no points, offline after a failed write: its probes must go out
    sched.submit_write(9, "holding", 0, [1])
    write = take(sched, 0.0)
    sched.on_failure(write, silent(write), 0.5)
    assert not sched.steady(req)
