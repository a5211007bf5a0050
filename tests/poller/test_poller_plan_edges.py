"""The planner at its edges: the cost arithmetic in exact numbers, the limits at
their bounds, the cuts' learning and withdrawal (docs/POLLER.md "Holes"), and
where `split` cuts a block.  Expected values come from the spec (Application
Protocol V1.1b 6.1-6.4: function codes, response sizes, per-request maxima),
docs/POLLER.md and hand arithmetic in the test, never from the planner."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest

from pyrtu.poller import Block, Cuts, Limits, Point, Wire, merge_pays, plan, split
from pyrtu.poller.plan import TCP_ROUND_TRIP, chunks, gaps, response_size

KEY = ("b", 1, "holding")


def pt(address: int, name: str | None = None, **kw: object) -> Point:
    fields: dict[str, object] = dict(bus="b", slave=1, table="holding", interval=1.0)
    fields.update(kw)
    return Point(name or f"p{address}", address=address, **fields)  # type: ignore[arg-type]


def block(*points: Point) -> Block:
    """One block over ``points`` as a read would cover them (first address to last end)."""
    lo = min(p.address for p in points)
    hi = max(p.end for p in points)
    return Block("b", 1, "holding", lo, hi - lo, tuple(points), min(p.interval for p in points))


def spans(blocks: list[Block]) -> list[tuple[int, int]]:
    return [(b.address, b.count) for b in blocks]


# -- the spec's numbers --------------------------------------------------------------------


def test_each_table_is_read_with_its_function_code() -> None:
    # Application Protocol V1.1b 6.1-6.4: 01 coils, 02 discrete inputs, 03 holding, 04 input
    for table, code in (("coils", 1), ("discrete_inputs", 2), ("holding", 3), ("input", 4)):
        kind = "bool" if table in ("coils", "discrete_inputs") else "uint16"
        (only,) = plan([pt(0, table=table, type=kind)], Wire(0.001, 0.0035))
        assert only.function == code, table


def test_response_size_is_the_spec_adu_for_every_count() -> None:
    # slave + function + byte count + data + CRC(2); bits packed 8 a byte, registers 2 bytes
    for n in range(1, 2001):
        for table in ("coils", "discrete_inputs"):
            assert response_size(table, n) == 1 + 1 + 1 + math.ceil(n / 8) + 2, (table, n)
    for n in range(1, 126):
        for table in ("holding", "input"):
            assert response_size(table, n) == 1 + 1 + 1 + 2 * n + 2, (table, n)


def test_wire_read_prices_request_turnaround_and_response_exactly() -> None:
    # integers in seconds, so every sum is exact: t3.5 100, 1 s a character, turnaround 1000
    wire = Wire(1.0, 100.0, 1000.0)
    # a read request is 8 bytes (slave, function, address 2, count 2, CRC 2)
    assert wire.read("holding", 10) == 100 + 8 + 1000 + (5 + 20)
    assert wire.read("coils", 17) == 100 + 8 + 1000 + (5 + 3)
    assert wire.read("holding", 10, turnaround=7.0) == 100 + 8 + 7 + (5 + 20)
    # no answer (a broadcast): the silence and the request only
    assert wire.frames(8, 0) == 100 + 8
    # the turnaround defaults to none at all
    assert Wire(1.0, 100.0).read("input", 1) == 100 + 8 + 7


def test_a_tcp_wire_costs_the_round_trip_whatever_the_size() -> None:
    # docs/POLLER.md: until measured, a round trip is taken as 2 ms
    assert TCP_ROUND_TRIP == 0.002
    assert Wire.tcp().read("holding", 1) == 0.002
    assert Wire.tcp().read("holding", 125) == 0.002
    assert Wire.tcp(0.005).read("coils", 2000) == 0.005
    assert Wire.tcp(0.005).frames(260, 0) == 0.0  # a broadcast holds the connection no time


@pytest.mark.parametrize(
    ("name", "lo", "hi"),
    [("max_registers", 1, 125), ("max_bits", 1, 2000), ("max_adu", 6, 256), ("max_gap", 0, 65535)],
)
def test_limits_are_accepted_exactly_within_their_bounds(name: str, lo: int, hi: int) -> None:
    # the spec's maxima (125 registers, 2000 bits, a 256-byte ADU); a gap of 0..65535
    Limits(**{name: lo})
    Limits(**{name: hi})
    for bad in (lo - 1, hi + 1, True, "3", 2.0):
        with pytest.raises(
            ValueError, match="^" + re.escape(f"{name}: must be an integer {lo}..{hi}, not ")
        ):
            Limits(**{name: bad})  # type: ignore[arg-type]


def test_a_limit_left_unset_does_not_excuse_the_ones_after_it() -> None:
    with pytest.raises(ValueError, match=r"^max_gap: "):
        Limits(max_registers=None, max_bits=None, max_adu=None, max_gap=-1)
    with pytest.raises(ValueError, match=r"^max_adu: "):
        Limits(max_adu=5)


def test_registers_and_bits_that_fit_a_response_of_max_adu_bytes() -> None:
    # the most n with 5 + 2n <= max_adu (registers) or 5 + ceil(n / 8) <= max_adu (bits),
    # at least one, at most the spec's maximum
    for adu in range(6, 257):
        regs = max((n for n in range(1, 126) if 5 + 2 * n <= adu), default=1)
        bits = max(n for n in range(1, 2001) if 5 + math.ceil(n / 8) <= adu)
        assert Limits(max_adu=adu).registers() == regs, adu
        assert Limits(max_adu=adu).bit_count() == bits, adu
        assert Limits(max_adu=adu).per_request("holding") == regs
        assert Limits(max_adu=adu).per_request("discrete_inputs") == bits
    assert Limits(max_bits=1).bit_count() == 1
    assert Limits(max_registers=1).registers() == 1
    assert Limits().registers() == 125 and Limits().bit_count() == 2000
    assert chunks("coils", 0, 9, Limits(max_adu=6)) == [(0, 8), (8, 1)]


def test_plan_values_are_immutable_and_slotted() -> None:
    """A `Block` is a key of the schedule and `Wire`/`Limits` are shared by its
    tasks: none may change after it is made, or carry stray attributes."""
    values = [
        (Limits(max_gap=3), "max_gap"),
        (Wire(0.001, 0.0035), "char"),
        (block(pt(0)), "count"),
    ]
    for value, name in values:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(value, name, 2)
        assert not hasattr(value, "__dict__"), type(value).__name__
    assert hash(block(pt(0))) == hash(block(pt(0)))


# -- merging -------------------------------------------------------------------------------


def test_a_gap_is_read_when_it_costs_exactly_a_second_request() -> None:
    """docs/POLLER.md: merged when ``wire(merged) / I <= wire(a) / I + wire(b) / I``.
    With 1 s a character, t3.5 of 7 and no turnaround, a read of n registers costs
    7 + 8 + 5 + 2n: two points 11 apart cost 7 + 13 + 2 x 12 = 44 merged, the same
    as 2 x (7 + 13 + 2) apart: merged (no more); 12 apart, 46 against 44: apart."""
    wire = Wire(1.0, 7.0)
    assert wire.read("holding", 12) == 2 * wire.read("holding", 1) == 44
    for base in (0, 100):  # the merged span is end - start, wherever the points are
        assert spans(plan([pt(base), pt(base + 11)], wire)) == [(base, 12)]
        assert spans(plan([pt(base), pt(base + 12)], wire)) == [(base, 1), (base + 12, 1)]
        a, b, c = block(pt(base)), block(pt(base + 11)), block(pt(base + 12))
        assert merge_pays(wire, a, b) and not merge_pays(wire, a, c)


def test_touching_points_share_a_request_and_a_gap_of_one_is_priced() -> None:
    # a point read every 0.1 s beside one read every 1000 s: contiguous, they are one
    # request (no gap to price); one register apart, the slow point's own request every
    # 1000 s is far cheaper than 2 more characters every 0.1 s
    wire = Wire(1.0, 7.0)
    fast, slow = pt(0, "fast", interval=0.1), pt(1, "slow", interval=1000.0)
    assert spans(plan([fast, slow], wire)) == [(0, 2)]
    assert spans(plan([fast, pt(2, "slow", interval=1000.0)], wire)) == [(0, 1), (2, 1)]


def test_a_block_may_end_right_before_a_cut_and_start_at_one() -> None:
    cuts = Cuts()
    cuts.add("b", 1, "holding", 3)
    assert spans(plan([pt(0), pt(1), pt(2), pt(3), pt(4)], Wire(1.0, 7.0), cuts=cuts)) == [
        (0, 3),
        (3, 2),
    ]
    assert cuts.between("b", 1, "holding", 2, 4) and not cuts.between("b", 1, "holding", 3, 9)
    assert not cuts.between("b", 1, "holding", 0, 3) and not cuts.between("b", 2, "holding", 0, 9)


# -- split and gaps ------------------------------------------------------------------------


def halves(*points: Point) -> tuple[list[int], list[int]] | None:
    out = split(block(*points))
    if out is None:
        return None
    lo, hi = out
    return sorted(p.address for p in lo.points), sorted(p.address for p in hi.points)


def test_split_cuts_at_the_widest_gap_the_first_of_equals() -> None:
    assert halves(pt(0), pt(3), pt(10)) == ([0, 3], [10])  # gaps 2 and 6
    assert halves(pt(0), pt(7), pt(10)) == ([0], [7, 10])  # gaps 6 and 2
    assert halves(pt(0), pt(5), pt(10)) == ([0], [5, 10])  # gaps 4 and 4: the first
    assert halves(pt(0), pt(5)) == ([0], [5])  # two points: one each
    # a gap of one register beats none: 0 | 2 3 4 5
    assert halves(pt(0), pt(2), pt(3), pt(4), pt(5)) == ([0], [2, 3, 4, 5])
    # 0 1 | 3 4 5 6: the gap of one, not the middle of the starts (4)
    assert halves(pt(0), pt(1), pt(3), pt(4), pt(5), pt(6)) == ([0, 1], [3, 4, 5, 6])
    # the gap is measured from the end of the widest point so far: uint32 at 0 covers 1
    assert halves(pt(0, "w", type="uint32"), pt(1), pt(4), pt(6)) == ([0, 1], [4, 6])
    # a point inside a wider one leaves no gap: the string covers 0..7
    assert halves(pt(0, "s", type="string", count=8), pt(2), pt(9)) == ([0, 2], [9])


def test_split_halves_contiguous_points_in_the_middle_of_their_starts() -> None:
    assert halves(pt(0), pt(1), pt(2), pt(3)) == ([0, 1], [2, 3])
    assert halves(pt(0), pt(1), pt(2), pt(3), pt(4)) == ([0, 1], [2, 3, 4])
    assert halves(pt(0), pt(1)) == ([0], [1])
    # overlapping points: starts 0, 1, 2 -> cut at 1
    ws = (pt(0, "a", type="uint32"), pt(1, "b", type="uint32"), pt(2, "c", type="uint32"))
    assert halves(*ws) == ([0], [1, 2])


def test_split_refuses_points_sharing_one_start() -> None:
    assert halves(pt(4)) is None
    assert halves(pt(4, "a"), pt(4, "b", type="int16"), pt(4, "c", type="uint32")) is None


def test_gaps_counts_the_holes_between_points() -> None:
    assert gaps(block(pt(0))) == 0
    assert gaps(block(pt(0), pt(1), pt(2))) == 0  # touching: no gap
    assert gaps(block(pt(0), pt(2))) == 1
    assert gaps(block(pt(0), pt(5), pt(10))) == 2
    assert gaps(block(pt(0), pt(5), pt(6), pt(10))) == 2
    # reach is the end of the widest point so far: the string covers 0..7
    assert gaps(block(pt(0, "s", type="string", count=8), pt(2), pt(8))) == 0
    assert gaps(block(pt(0, "s", type="string", count=8), pt(2), pt(9))) == 1


# -- the cuts' learning (docs/POLLER.md "Holes") -------------------------------------------


def test_a_suspected_cut_is_withdrawn_by_a_later_cut_inside_its_block() -> None:
    """0 5 10 answered exception 2: two gaps, the cut at 5 only suspected.  5..10 then
    answers exception 2 too: one gap (6..9), the cut at 10 proven; that hole alone
    explains the first answer, so the cut at 5 is withdrawn."""
    cuts = Cuts()
    first = block(pt(0), pt(5), pt(10))
    assert cuts.learn(first, 5, proven=False) == []
    assert cuts.cuts[KEY] == {5}
    assert cuts.learn(block(pt(5), pt(10)), 10, proven=True) == [5]
    assert cuts.cuts[KEY] == {10}
    # the planner reads across 5 again, not across 10
    assert spans(plan([pt(0), pt(5), pt(10)], Wire(1.0, 100.0), cuts=cuts)) == [(0, 6), (10, 1)]


def test_learning_a_cut_again_withdraws_nothing() -> None:
    cuts = Cuts()
    first = block(pt(0), pt(5), pt(10))
    assert cuts.learn(first, 5, proven=False) == []
    assert cuts.learn(first, 5, proven=False) == []
    assert cuts.cuts[KEY] == {5}


def test_a_proven_cut_is_never_withdrawn_by_learning() -> None:
    cuts = Cuts()
    assert cuts.learn(block(pt(0), pt(5), pt(10)), 5, proven=True) == []
    assert cuts.learn(block(pt(5), pt(10)), 10, proven=True) == []
    assert cuts.cuts[KEY] == {5, 10}


def test_a_cut_kept_for_good_is_never_withdrawn() -> None:
    cuts = Cuts()
    cuts.add("b", 1, "holding", 5)
    assert cuts.learn(block(pt(0), pt(5), pt(10)), 10, proven=True) == []
    assert cuts.cuts[KEY] == {5, 10}
    # point 0 does not exist: the cut learned from the block that held it goes, not 5
    assert cuts.forget_point("b", 1, "holding", 0) == [10]
    assert cuts.cuts[KEY] == {5}


def test_only_a_gap_inside_the_suspected_block_withdraws_its_cut() -> None:
    """The new cut's gap runs from the end of the points before it to the cut: the
    suspected cut goes when that gap starts at or after its block's first address
    and the new cut lies before its block's end."""

    def after(origin: Block, failing: Block, cut: int) -> list[int]:
        cuts = Cuts()
        cuts.learn(origin, 20, proven=False)
        return cuts.learn(failing, cut, proven=True)

    origin = block(pt(4), pt(20), pt(30))  # 4..30, the suspected cut at 20
    string = pt(0, "s", type="string", count=4)  # 0..3: the gap after it starts at 4
    assert after(origin, block(string, pt(10)), 10) == [20]  # gap 4..9, inside 4..30
    assert after(origin, block(pt(0), pt(10)), 10) == []  # gap 1..9 starts before 4
    assert after(origin, block(pt(4), pt(10)), 10) == [20]  # gap 5..9
    later = block(pt(5), pt(20), pt(30))  # 5..30
    assert after(later, block(string, pt(10)), 10) == []  # gap 4..9 starts before 5
    # the new cut inside the block, at its last address, or beyond it
    assert after(origin, block(pt(25), pt(30)), 30) == [20]
    assert after(origin, block(pt(26), pt(35)), 35) == []
    # a cut at its end (31: the first address it did not read) is not inside it
    assert after(origin, block(pt(29), pt(30), pt(31), pt(32)), 31) == []
    # the gap ends at the new cut: the points at and after it do not move its start
    at5, at6 = block(pt(5), pt(20), pt(30)), block(pt(6), pt(20), pt(30))
    assert after(at5, block(pt(4), pt(10), pt(12)), 10) == [20]  # gap 5..9
    assert after(at6, block(pt(4), pt(10), pt(12)), 10) == []


def test_a_suspected_cut_keeps_the_block_it_came_from_unless_proven() -> None:
    cuts = Cuts()
    cuts.learn(block(pt(0), pt(5), pt(10)), 5, proven=False)  # from 0..10
    cuts.learn(block(pt(2), pt(5), pt(8)), 5, proven=False)  # again, from 2..8: kept 0..10
    assert cuts.forget_point("b", 1, "holding", 10) == [5]
    cuts.learn(block(pt(0), pt(5), pt(10)), 5, proven=False)
    cuts.learn(block(pt(2), pt(5)), 5, proven=True)  # proven from 2..5: that one now
    assert cuts.forget_point("b", 1, "holding", 10) == []
    assert cuts.forget_point("b", 1, "holding", 2) == [5]


@pytest.mark.parametrize(
    ("address", "withdrawn"), [(3, False), (4, True), (17, True), (29, True), (30, False)]
)
def test_forgetting_a_point_withdraws_the_cuts_of_the_blocks_that_held_it(
    address: int, withdrawn: bool
) -> None:
    cuts = Cuts()
    cuts.learn(block(pt(4), pt(20), pt(29)), 20, proven=True)  # the block read 4..29
    assert cuts.forget_point("b", 1, "holding", address) == ([20] if withdrawn else [])
    assert cuts.cuts[KEY] == (set() if withdrawn else {20})
    assert cuts.forget_point("b", 2, "holding", 20) == []  # another slave's map


def test_a_cut_withdrawn_8_times_stays_for_good() -> None:
    """docs/POLLER.md: a cut withdrawn 8 times stays for good (a bound on learning)."""
    cuts = Cuts()
    origin = block(pt(0), pt(5), pt(10))
    for n in range(8):
        assert cuts.learn(origin, 5, proven=False) == []
        assert cuts.forget_point("b", 1, "holding", 0) == [5], n
        assert cuts.cuts[KEY] == set(), n
    cuts.learn(origin, 5, proven=False)
    cuts.forget_point("b", 1, "holding", 0)  # the 9th: kept
    assert cuts.cuts[KEY] == {5}
    assert cuts.forget_point("b", 1, "holding", 0) == []
    assert cuts.learn(block(pt(5), pt(10)), 10, proven=True) == []
    assert cuts.cuts[KEY] == {5, 10}


def test_learning_withdraws_by_the_same_count() -> None:
    # withdrawals by learning and by forgetting share the one count of 8
    cuts = Cuts()
    for n in range(8):
        cuts.learn(block(pt(0), pt(5), pt(10)), 5, proven=False)
        withdraw = (
            cuts.learn(block(pt(5), pt(10)), 10, proven=True)
            if n % 2
            else cuts.forget_point("b", 1, "holding", 10)
        )
        assert withdraw == [5], n
        cuts.cuts[KEY].discard(10)
    cuts.learn(block(pt(0), pt(5), pt(10)), 5, proven=False)
    cuts.forget_point("b", 1, "holding", 10)
    assert 5 in cuts.cuts[KEY]
