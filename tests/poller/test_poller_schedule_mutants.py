"""The bus scheduler where the mutation run (docs/MUTATION.md) found it untested,
driven by hand on a fake clock: the defaults and the spec's frame sizes of FC 15 and
FC 22, the stamps' offset on every event, the order of the probes, the confirmation
a slave going offline cancels, the blocks a returning slave resumes (its own only),
the load checked on a failure, the silence timer and the first probe after it,
the wire time of a clock step, the cut a block of one gap proves.  Expected values
come from docs/POLLER.md, the spec (Application Protocol V1.1b 6.11, 6.16) and hand
arithmetic, never from the scheduler."""

from __future__ import annotations

import pytest
from test_poller_schedule_edges import WIRE, pt, silent

from pyrtu.pdu.errors import ExceptionResponseError, FrameError
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
from pyrtu.poller.events import Event

#: a read of one holding register: t3.5, the 8-byte request, the 7-byte answer
READ_ONE = 0.004 + 8 * 0.001 + 7 * 0.001
#: 0.25 s a character, t3.5 of 1 s: a read of one register holds the wire 4.75 s
SLOW = Wire(0.25, 1.0)


def hole(req: ScheduledRequest) -> ExceptionResponseError:
    return ExceptionResponseError(req.slave, req.function, 2)


def take(sched: BusScheduler, now: float) -> ScheduledRequest:
    req = sched.next_request(now)
    assert req is not None, now
    return req


def states(events: list[Event]) -> list[tuple[int, bool, float]]:
    return [(e.slave, e.online, e.time) for e in events if isinstance(e, SlaveState)]


def spans(sched: BusScheduler) -> list[tuple[int, int, int]]:
    return sorted((b.slave, b.address, b.count) for b in sched.blocks)


def registers_of_one(sched: BusScheduler) -> list[tuple[int, int]]:
    """Slave 1's blocks of holding registers: (address, count)."""
    return sorted(
        (b.address, b.count) for b in sched.blocks if (b.slave, b.table) == (1, "holding")
    )


# -- settings ------------------------------------------------------------------------------


def test_the_default_offline_after_is_three_failures() -> None:
    """docs/POLLER.md: ``offline_after`` consecutive failures (default 3)."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    now, seen = 0.0, []
    for _ in range(3):
        req = take(sched, now)
        now += 0.125
        seen.append(states(sched.on_failure(req, silent(req), now)))
    assert seen == [[], [], [(1, False, 0.375)]]


def test_the_settings_after_the_line_are_keyword_only() -> None:
    """A sixth positional argument is refused, not taken as ``share``."""
    with pytest.raises(TypeError):
        BusScheduler("b", [pt(0)], WIRE, None, None, 0.5)  # type: ignore[call-arg]
    sched = BusScheduler(bus="b", points=[pt(0)], wire=WIRE, limits=None, default_limits=None)
    assert sched.share == 0.05


def test_a_point_exactly_as_wide_as_the_maximum_per_request_is_accepted() -> None:
    """docs/POLLER.md: only a point *wider* than the maximum is a configuration error."""
    sched = BusScheduler("b", [pt(0, type="uint32")], WIRE, {1: Limits(max_registers=2)})
    assert spans(sched) == [(1, 0, 2)]


# -- the requests' wire cost from the spec's frames ----------------------------------------


def test_a_mask_write_is_fc_22_of_one_register_and_costs_its_frames() -> None:
    """Application Protocol 6.16: request slave, 22, address 2, AND mask 2, OR mask 2,
    CRC 2 = 10 bytes; the answer echoes it (10 bytes)."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = sched.submit_mask_write(1, 4, 0x00F2, 0x0025)
    assert (req.kind, req.slave, req.table, req.address, req.count, req.function) == (
        "write", 1, "holding", 4, 1, 22,
    )  # fmt: skip
    assert req.values == (0x00F2, 0x0025)
    assert req.cost == pytest.approx(0.004 + 10 * 0.001 + 10 * 0.001)


@pytest.mark.parametrize(("coils", "value_bytes"), [(7, 1), (8, 1), (9, 2), (16, 2), (17, 3)])
def test_fc_15_packs_its_coils_eight_a_byte(coils: int, value_bytes: int) -> None:
    """Application Protocol 6.11: the byte count is ceil(n / 8), at the byte's edge."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = sched.submit_write(1, "coils", 0, [True] * coils)
    # t3.5; slave, 15, address 2, quantity 2, byte count, the values, CRC 2; the
    # 8-byte answer of address and quantity
    assert req.cost == pytest.approx(0.004 + (9 + value_bytes) * 0.001 + 8 * 0.001)


def test_a_probe_of_a_holding_register_costs_one_registers_read() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=1)
    req = take(sched, 0.0)
    sched.on_failure(req, silent(req), 0.125)
    probe = take(sched, 0.625)
    assert (probe.kind, probe.table, probe.count) == ("probe", "holding", 1)
    # the answer: slave, 3, byte count, 2 bytes, CRC 2
    assert probe.cost == pytest.approx(READ_ONE)


# -- the stamps ----------------------------------------------------------------------------


def test_every_event_is_stamped_with_the_offset() -> None:
    """docs/POLLER.md: the scheduler adds its ``stamp_offset`` to the driver's clock."""
    offset = 1000.0
    sched = BusScheduler("b", [pt(0)], SLOW, offline_after=1, stamp_offset=offset)
    req = take(sched, 0.0)
    events = sched.on_response(req, [7], 4.75)  # online; a load of 4.75: overloaded
    assert states(events) == [(1, True, offset + 4.75)]
    assert [(e.value, e.time) for e in events if isinstance(e, Update)] == [(7, offset + 4.75)]
    assert [(e.overloaded, e.time) for e in events if isinstance(e, Overload)] == [
        (True, offset + 4.75)
    ]
    req = take(sched, 5.0)
    events = sched.on_failure(req, silent(req), 6.0)
    assert states(events) == [(1, False, offset + 6.0)]
    assert [(e.overloaded, e.time) for e in events if isinstance(e, Overload)] == [
        (False, offset + 6.0)
    ]
    probe = take(sched, 7.0)
    assert probe.kind == "probe"
    events = sched.on_response(probe, [0], 8.0)
    assert states(events) == [(1, True, offset + 8.0)]

    dropping = BusScheduler("b", [pt(0)], WIRE, stamp_offset=offset)
    req = take(dropping, 0.0)
    events = dropping.on_failure(req, hole(req), 0.5)
    assert [(e.point.name, e.time) for e in events if isinstance(e, PointDropped)] == [
        ("s1.0", offset + 0.5)
    ]


# -- the confirmation ----------------------------------------------------------------------


def test_a_slave_going_offline_cancels_its_own_confirmation_only() -> None:
    """A write that went ahead of a confirmation takes the slave offline: no
    confirmation of it is left (nothing is due before its probe); a confirmation
    of another slave pending meanwhile still goes next."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=2)
    poll = take(sched, 0.0)
    write = sched.submit_write(1, "holding", 3, [1])
    sched.on_failure(poll, silent(poll), 0.125)  # a confirmation of slave 1 is due
    assert take(sched, 0.125) is write  # the queued write goes first
    assert states(sched.on_failure(write, silent(write), 0.25)) == [(1, False, 0.25)]
    assert sched.deadline() == 0.25 + 0.5  # alone on the bus: the probe's back-off

    points = [pt(0, slave=1, interval=10.0), pt(0, slave=2, interval=10.0)]
    sched = BusScheduler("b", points, WIRE, offline_after=2)
    first = take(sched, 0.0)
    assert first.slave == 1
    sched.on_response(first, [0], 0.125)  # slave 1 next due at 10
    poll = take(sched, 0.125)
    assert poll.slave == 2
    to_one = sched.submit_write(1, "holding", 3, [1])
    to_two = sched.submit_write(2, "holding", 3, [1])
    sched.on_failure(poll, silent(poll), 0.25)  # slave 2: one failure
    assert take(sched, 0.25) is to_one
    sched.on_failure(to_one, silent(to_one), 0.375)  # slave 1: one failure, to confirm
    assert take(sched, 0.375) is to_two
    assert states(sched.on_failure(to_two, silent(to_two), 0.5)) == [(2, False, 0.5)]
    confirm = take(sched, 0.5)  # slave 1's block, ahead of its due time (10)
    assert (confirm.kind, confirm.slave) == ("poll", 1)


def test_a_block_in_flight_is_not_taken_again_to_confirm_a_failure() -> None:
    """The confirmation is the slave's earliest-due block waiting in the schedule:
    not one in flight, even when that one is due earlier."""
    sched = BusScheduler("b", [pt(0, interval=1.0), pt(500, interval=10.0)], WIRE)
    in_flight = take(sched, 0.0)  # next due at 1
    assert in_flight.address == 0
    other = take(sched, 0.0)
    assert other.address == 500
    sched.on_response(other, [0], 0.125)  # next due at 10
    write = sched.submit_write(1, "holding", 3, [1])
    assert take(sched, 0.125) is write
    sched.on_failure(write, silent(write), 0.25)
    confirm = take(sched, 0.25)
    assert (confirm.kind, confirm.address) == ("poll", 500)


# -- health --------------------------------------------------------------------------------


def test_a_slave_back_online_resumes_its_own_blocks_only() -> None:
    """docs/POLLER.md: an answer brings the slave back with its blocks due at once;
    another slave's blocks keep their beat, an offline one's stay out."""
    points = [pt(0, slave=s, interval=10.0) for s in (1, 2, 3)]
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=1, backoff=5, max_backoff=5)
    req = take(sched, 0.0)
    assert req.slave == 1
    sched.on_response(req, [0], 0.125)  # next due at 10
    for slave, end in ((2, 0.25), (3, 0.375)):
        req = take(sched, end - 0.125)
        assert req.slave == slave
        sched.on_failure(req, silent(req), end)  # offline, probed 5 s later
    probe = take(sched, 5.25)
    assert (probe.kind, probe.slave) == ("probe", 2)
    assert states(sched.on_response(probe, [0], 5.3125)) == [(2, True, 5.3125)]
    req = take(sched, 5.3125)
    assert (req.kind, req.slave) == ("poll", 2)
    sched.on_response(req, [0], 5.34375)
    assert sched.next_request(5.34375) is None
    assert sched.deadline() == 5.375  # slave 3's probe; slave 1 is due at 10


def test_the_earliest_due_probe_goes_first() -> None:
    """Two offline slaves whose back-offs ran out: the one due earlier is probed
    first (earliest deadline first), whichever was declared first."""
    points = [pt(0, slave=1), pt(0, slave=2)]
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=1, backoff=0.5, max_backoff=0.5)
    req = take(sched, 0.0)
    assert req.slave == 1
    sched.on_failure(req, silent(req), 0.25)  # probe due at 0.75
    req = take(sched, 0.25)
    assert req.slave == 2
    sched.on_failure(req, silent(req), 0.375)  # probe due at 0.875
    probe = take(sched, 1.0)
    assert (probe.kind, probe.slave) == ("probe", 1)
    sched.on_failure(probe, silent(probe), 1.125)
    probe = take(sched, 1.125)
    assert (probe.kind, probe.slave) == ("probe", 2)

    # the other way round: the slave declared second is due first
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=1, backoff=0.5, max_backoff=0.5)
    first = take(sched, 0.0)
    second = take(sched, 0.0)
    assert (first.slave, second.slave) == (1, 2)
    sched.on_failure(second, silent(second), 0.125)  # probe due at 0.625
    sched.on_failure(first, silent(first), 0.25)  # probe due at 0.75
    probe = take(sched, 1.0)
    assert (probe.kind, probe.slave) == ("probe", 2)


def test_probes_due_at_the_same_time_go_in_declaration_order() -> None:
    """Ties go as the polls' do (by due time, then declaration): slave 1's probe
    and slave 2's are both due at 0.5 (the share floor: each failure's wire time
    x (1 / 0.5 - 1) while slave 3 is online)."""
    points = [pt(0, slave=1), pt(0, slave=2), pt(0, slave=3, interval=100.0)]
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=0.5, backoff=0.0625)
    req = take(sched, 0.0)
    assert req.slave == 1
    sched.on_failure(req, silent(req), 0.25)  # 0.25 on the wire: probe at 0.25 + 0.25
    req = take(sched, 0.25)
    assert req.slave == 2
    sched.on_failure(req, silent(req), 0.375)  # 0.125: probe at 0.375 + 0.125
    req = take(sched, 0.375)
    assert req.slave == 3
    sched.on_response(req, [0], 0.4375)
    assert sched.deadline() == 0.5
    probe = take(sched, 0.5)
    assert (probe.kind, probe.slave) == ("probe", 1)


def test_a_silenced_request_failing_keeps_the_first_back_off() -> None:
    """docs/POLLER.md: taken offline by the silence timer, the slave's first probe
    waits as it would have after that request's failure: the initial back-off
    (0.5 s; alone on the bus, no share floor) from the failure, not doubled."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=2, timeout=0.125)
    req = take(sched, 0.0)
    sched.on_failure(req, silent(req), 0.25)  # its request ended at 0.25 - 0.125 at latest
    confirm = take(sched, 0.25)
    due = sched.offline_due(confirm)
    assert due == 0.125 + 2 * 0.125
    assert states(sched.on_silence(confirm, due)) == [(1, False, due)]
    assert sched.on_failure(confirm, silent(confirm), 0.4375) == []
    assert sched.deadline() == 0.4375 + 0.5


def test_the_silence_counts_from_the_first_of_the_failures_back_to_back() -> None:
    """docs/POLLER.md: the timer needs the requests back to back; a transaction
    between two failures starts the count again from the later one's request."""
    points = [pt(0, slave=1), pt(0, slave=2)]
    sched = BusScheduler("b", points, WIRE, offline_after=3, timeout=0.125)
    req = take(sched, 0.0)
    assert req.slave == 1
    write = sched.submit_write(2, "holding", 0, [1])
    sched.on_failure(req, silent(req), 0.25)
    assert take(sched, 0.25) is write  # between the failures
    sched.on_response(write, None, 0.3125)
    second = take(sched, 0.3125)
    assert (second.slave, second.kind) == (1, "poll")
    sched.on_failure(second, silent(second), 0.5625)  # its request ended at 0.4375
    third = take(sched, 0.5625)
    assert third.slave == 1
    assert sched.offline_due(third) == 0.4375 + 3 * 0.125


def test_a_port_failure_of_a_write_to_a_slave_without_points() -> None:
    """docs/POLLER.md: a failed port blames no slave; a slave known only from a
    write (no health kept yet) is no exception to that."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    write = sched.submit_write(9, "holding", 0, [1])
    assert take(sched, 0.0) is write
    sched.on_port_failure(write)
    assert sched.online(9) is None
    poll = take(sched, 0.0)
    assert (poll.slave, poll.kind) == (1, "poll")


def test_a_port_failure_meanwhile_leaves_the_silenced_requests_outcome_alone() -> None:
    """A request of the slave fails on its port while the silenced one is still in
    flight: that one's failure still gives the first probe the initial back-off."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=2, timeout=0.125)
    req = take(sched, 0.0)
    sched.on_failure(req, silent(req), 0.25)
    confirm = take(sched, 0.25)
    due = sched.offline_due(confirm)
    assert due is not None
    sched.on_silence(confirm, due)
    write = sched.submit_write(1, "holding", 0, [1])
    assert take(sched, due) is write
    sched.on_port_failure(write)
    sched.on_failure(confirm, silent(confirm), 0.4375)
    assert sched.deadline() == 0.4375 + 0.5


# -- the load and the figures --------------------------------------------------------------


def test_a_slave_going_offline_checks_the_load_at_once() -> None:
    """docs/POLLER.md: an `Overload` event when the load crosses 1 and another when
    it ends; a slave's blocks leave the load when it goes offline (each block 4.75 s
    of wire every 7.6 s: 0.625; both 1.25)."""
    points = [pt(0, slave=1, interval=7.6), pt(0, slave=2, interval=7.6)]
    sched = BusScheduler("b", points, SLOW, offline_after=1)
    req = take(sched, 0.0)
    assert req.slave == 1
    events = sched.on_response(req, [0], 4.75)  # answered in its frames' time
    (over,) = [e for e in events if isinstance(e, Overload)]
    assert over.overloaded is True and over.load == pytest.approx(1.25)
    req = take(sched, 4.75)
    assert req.slave == 2
    events = sched.on_failure(req, silent(req), 5.75)
    (over,) = [e for e in events if isinstance(e, Overload)]
    assert over.overloaded is False and over.load == pytest.approx(0.625)


@pytest.mark.parametrize(("interval", "overloaded"), [(4.75, False), (3.8, True), (2.375, True)])
def test_an_overload_event_only_above_a_load_of_one(interval: float, overloaded: bool) -> None:
    """The first answer brings the slave online and the load is checked: 4.75 s of
    wire every 4.75 s is a load of exactly 1 (no overload), every 3.8 s 1.25, every
    2.375 s 2."""
    sched = BusScheduler("b", [pt(0, interval=interval)], SLOW)
    req = take(sched, 0.0)
    events = sched.on_response(req, [0], 4.75)  # answered in its frames' time
    over = [(e.overloaded, e.load) for e in events if isinstance(e, Overload)]
    assert over == ([(True, 4.75 / interval)] if overloaded else [])


def test_the_load_is_first_computed_on_the_16th_failure() -> None:
    """Nothing computed yet: no load (0, not a made-up figure); failures that change
    no slave's state compute it every 16 transactions, the first time on the 16th."""
    sched = BusScheduler("b", [pt(0)], WIRE, offline_after=100)
    assert sched.last_load == 0.0
    now, seen = 0.0, []
    for _ in range(16):
        req = take(sched, now)
        now += 0.125
        sched.on_failure(req, FrameError("bad crc", 1, 3), now)
        seen.append(sched.last_load)
    assert seen[:15] == [0.0] * 15
    assert seen[15] == pytest.approx(READ_ONE / 1.0)


def test_an_answer_faster_than_its_frames_measures_no_negative_turnaround() -> None:
    """A clock coarser than the frames: the turnaround measured is never below 0, so
    the block costs at least its frames (docs/POLLER.md: transaction time minus the
    frames' time)."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.010)  # 10 ms, the frames take 19
    assert sched.load() == pytest.approx(READ_ONE / 1.0)


def test_a_clock_step_counts_no_negative_wire_time() -> None:
    """Answers stamped before their requests, a request issued before the last
    answer's stamp, a report asked before it: the wire time never shrinks and the
    utilisation stays a fraction."""
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 1.0)
    sched.on_response(req, [0], 0.5)
    assert sched.slave_stats()[1].busy == 0.0
    req = take(sched, 1.5)  # 1 s after the last answer: a whole t3.5 before it
    sched.on_response(req, [0], 2.0)
    assert sched.slave_stats()[1].busy == pytest.approx(0.5 + 0.004)
    write = sched.submit_write(1, "holding", 0, [1])
    assert take(sched, 1.875) is write  # before the last answer (2.0): no silence
    sched.on_response(write, None, 1.9375)
    assert sched.slave_stats()[1].busy == pytest.approx(0.5 + 0.004 + 0.0625)
    assert sched.utilisation(1.25) == 1.0  # 0.5665 s busy in the 0.25 s since 1.0


def test_the_silence_before_a_request_counts_from_the_window_start() -> None:
    """docs/POLLER.md: only what falls inside the statistics' window counts: of the
    t3.5 silence before a request, the part after `reset_stats`."""
    sched = BusScheduler("b", [pt(0, interval=0.0078125)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.0078125)
    sched.reset_stats(0.0087890625)  # 1 ms before the next request
    req = take(sched, 0.0097656250)
    sched.on_response(req, [0], 0.0175781250)
    # its 7.8125 ms and the 0.9765625 ms of silence since the window started
    assert sched.slave_stats()[1].busy == pytest.approx(0.0078125 + 0.0009765625)


def test_reset_stats_starts_the_busy_time_from_nothing() -> None:
    sched = BusScheduler("b", [pt(0)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.5)
    assert sched.utilisation(1.0) == 0.5
    sched.reset_stats(1.0)
    assert sched.utilisation(2.0) == 0.0 and sched.report(2.0).utilisation == 0.0


def test_a_block_exactly_one_interval_late_is_not_lagging() -> None:
    """docs/POLLER.md: lagging is *more* than one interval late."""
    sched = BusScheduler("b", [pt(0, interval=0.5)], WIRE)
    req = take(sched, 0.0)
    sched.on_response(req, [0], 0.0625)
    req = take(sched, 1.0)  # due at 0.5: exactly 0.5 late
    sched.on_response(req, [0], 1.0625)
    assert sched.lagging() == () and sched.report(1.0625).lagging == ()


def test_start_at_moves_the_beat() -> None:
    """`start_at`: every block first due then, and its beat from then on."""
    sched = BusScheduler("b", [pt(0, interval=1.0)], WIRE)
    sched.start_at(5.0)
    assert sched.deadline() == 5.0 and sched.next_request(4.5) is None
    req = take(sched, 5.0)
    sched.on_response(req, [0], 5.125)
    assert sched.deadline() == 6.0
    assert sched.lagging() == ()


# -- holes ---------------------------------------------------------------------------------


def _answer_until(
    sched: BusScheduler, now: float, address: int, count: int
) -> tuple[ScheduledRequest, float]:
    """Answer every request from ``now`` on (1/32 s each) until slave 1's read of
    holding registers ``address``..+``count``: that request and the time."""
    while True:
        req = take(sched, now)
        if (req.slave, req.table, req.address, req.count) == (1, "holding", address, count):
            return req, now
        now += 0.03125
        sched.on_response(req, [0] * req.count, now)


def _one_gap_then_a_missing_point(extra: list[Point]) -> tuple[BusScheduler, float]:
    """Points 0, 1 (missing) and 10 of slave 1: read as one block of one gap, which
    answers exception 2; then the half 0..1, which answers it again.  Returns the
    scheduler and the time."""
    sched = BusScheduler("b", [pt(0), pt(1, "missing"), pt(10), *extra], WIRE)
    assert registers_of_one(sched) == [(0, 11)]
    req, now = _answer_until(sched, 0.0, 0, 11)
    now += 0.03125
    sched.on_failure(req, hole(req), now)
    # split at the widest gap (the only one): 0..1 and 10; the cut at 10 is proven
    assert registers_of_one(sched) == [(0, 2), (10, 1)]
    req, now = _answer_until(sched, now, 0, 2)
    now += 0.03125
    sched.on_failure(req, hole(req), now)
    return sched, now


def test_a_cut_from_a_block_of_one_gap_is_proven() -> None:
    """docs/POLLER.md: a cut from a block with one gap is proven (the points are
    presumed to exist: the hole is in that gap); a later exception 2 inside that
    block (0..1 split in the middle) does not withdraw it: 0, 1 and 10 apart."""
    sched, _ = _one_gap_then_a_missing_point([])
    assert registers_of_one(sched) == [(0, 1), (1, 1), (10, 1)]


def test_cuts_withdrawn_replan_that_slaves_table_only() -> None:
    """Point 1 does not exist: dropped, the cuts learned from blocks that held it
    withdrawn and slave 1's holding registers planned again (due at once); slave
    2's block (and slave 1's coils) keep their beat (due at 10), and the blocks
    planned away are due no more (`deadline`)."""
    extra = [pt(0, slave=2, interval=10.0), pt(0, "coil", table="coils", interval=10.0)]
    sched, now = _one_gap_then_a_missing_point(extra)
    req, now = _answer_until(sched, now, 1, 1)
    now += 0.03125
    dropped = [e for e in sched.on_failure(req, hole(req), now) if isinstance(e, PointDropped)]
    assert [e.point.name for e in dropped] == ["missing"]
    # planned again without the cuts: 0 and 10 apart all the same (one read of 0..10,
    # 4 + 8 + 5 + 22 = 39 ms, costs more than two of one register, 2 x 19 ms)
    assert registers_of_one(sched) == [(0, 1), (10, 1)]
    dropped_at, seen = now, []
    while (deadline := sched.deadline()) is not None and deadline <= now:
        req = take(sched, now)
        seen.append((req.slave, req.table, req.address))
        now += 0.03125
        sched.on_response(req, [0] * req.count, now)
    assert seen == [(1, "holding", 0), (1, "holding", 10)]
    # the earliest due: the new blocks' next beat (the old blocks' turns are gone)
    assert sched.deadline() == dropped_at + 1.0


def test_the_deadline_skips_an_offline_slaves_blocks() -> None:
    """deadline(): the earliest time next_request has something; a block of a slave
    gone offline (due at 0.5) is not it: the probe is (0.5 s after the failure)."""
    points = [pt(0, slave=1), pt(0, slave=2, interval=0.5), pt(500, slave=2, interval=0.5)]
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=1)
    req = take(sched, 0.0)
    assert (req.slave, req.address) == (1, 0)
    sched.on_response(req, [0], 0.015625)  # next due at 1
    req = take(sched, 0.015625)
    assert (req.slave, req.address) == (2, 0)
    sched.on_response(req, [0], 0.03125)  # next due at 0.5
    req = take(sched, 0.03125)
    assert (req.slave, req.address) == (2, 500)
    sched.on_failure(req, silent(req), 0.046875)
    assert sched.deadline() == 0.046875 + 0.5


def test_probes_are_found_again_after_every_return() -> None:
    """The scheduler counts its offline slaves to skip looking for probes when there
    are none (the common case, on every request): offline, back, offline again, the
    probe is due each time (backoff 5 s after the failure, docs/POLLER.md); and back
    for good, the count is 0 (nothing is looked for)."""
    points = [pt(0, slave=1, interval=10.0), pt(0, slave=2, interval=10.0)]
    sched = BusScheduler("b", points, WIRE, offline_after=1, share=1, backoff=5, max_backoff=5)
    now = 0.0
    for _ in range(2):
        for slave in (1, 2):
            req = take(sched, now)
            assert (req.kind, req.slave) == ("poll", slave)
            now += 0.125
            sched.on_failure(req, silent(req), now)  # offline, probed 5 s later
        assert sched.deadline() == now - 0.125 + 5  # slave 1's probe
        for slave in (1, 2):
            probe = take(sched, now + 5)
            assert (probe.kind, probe.slave) == ("probe", slave)
            sched.on_response(probe, [0], now + 5.0625)
        now += 5.0625
    assert sched._offline_count == 0  # (white box: the count the probes are looked for by)


def test_a_probes_answer_measures_the_slaves_turnaround() -> None:
    """A probe has no task of the schedule: its frames are the wire's for a read of
    one register (t3.5 4 ms, the 8-byte request, the 7-byte answer at 1 ms a
    character: 19 ms, `Wire.read`), and what its transaction took beyond them is the
    turnaround the slave's blocks then cost (docs/POLLER.md, "Load").  Answered
    25 ms after it was issued: 25 - 19 = 6 ms; its block of one register every 10 s
    then costs 4 + 8 + 6 + 7 = 25 ms (the probe's own time), a load of 0.0025."""
    sched = BusScheduler("b", [pt(0, interval=10.0)], WIRE, offline_after=1, share=1,
                         backoff=5, max_backoff=5)  # fmt: skip
    req = take(sched, 0.0)
    sched.on_failure(req, silent(req), 0.125)  # offline, probed 5 s later
    probe = take(sched, 5.125)
    assert probe.kind == "probe"
    sched.on_response(probe, [0], 5.15)
    assert sched.load() == pytest.approx(0.025 / 10.0)
