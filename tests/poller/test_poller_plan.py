"""Points and coalescing as pure functions: types and decoding, gaps, the maximum
per request, holes learned from exception 2, mixed intervals."""

from __future__ import annotations

import math

import pytest

from pyrtu.pdu.data import encode_float32, encode_string, encode_uint32
from pyrtu.poller import Block, Cuts, Limits, Point, PointError, Wire, merge_pays, plan, split
from pyrtu.poller.plan import chunks, response_size

#: 19200 baud 8E1: 11 bits a character, t3.5 = 2.005 ms; turnaround t3.5
WIRE = Wire(11 / 19200, 0.002005, 0.002005)


def pt(address: int, name: str | None = None, **kw: object) -> Point:
    fields: dict[str, object] = dict(bus="b", slave=1, table="holding", interval=1.0)
    fields.update(kw)
    return Point(name or f"p{address}", address=address, **fields)  # type: ignore[arg-type]


# -- points -------------------------------------------------------------------------------


def test_point_defaults_and_sizes() -> None:
    assert pt(0).type == "uint16" and pt(0).size == 1
    assert pt(0, table="coils").type == "bool"
    assert pt(0, type="float32").size == 2
    assert pt(0, type="string", count=8).size == 8 and pt(0, type="string", count=8).end == 8
    assert pt(0, type="int32", order="cdab").order == "CDAB"


@pytest.mark.parametrize(
    ("kw", "field", "words"),
    [
        ({"address": -1}, "address", "0..65535"),
        ({"address": 70000}, "address", "0..65535"),
        ({"slave": 256}, "slave", "0..255"),
        ({"slave": True}, "slave", "integer"),
        ({"table": "registers"}, "table", "holding"),
        ({"type": "float128"}, "type", "float64"),
        ({"table": "coils", "type": "uint16"}, "type", "bool"),
        ({"type": "bool"}, "type", "bit = 0..15"),
        ({"order": "ABDC"}, "order", "CDAB"),
        ({"type": "string"}, "count", "1..125"),
        ({"count": 3}, "count", "strings only"),
        ({"interval": 0}, "interval", "greater than 0"),
        ({"interval": math.inf}, "interval", "finite"),
        ({"scale": 0}, "scale", "not be 0"),
        ({"deadband": -1}, "deadband", ">= 0"),
        ({"address": 65535, "type": "uint32"}, "address", "past 65535"),
        ({"type": "string", "count": 2, "scale": 2}, "scale", "no scale"),
        ({"name": ""}, "name", "non-empty"),
    ],
)
def test_point_validation_names_the_field(kw: dict[str, object], field: str, words: str) -> None:
    args: dict[str, object] = dict(name="x", bus="b", slave=1, table="holding", address=0)
    args.update(kw)
    with pytest.raises(PointError) as e:
        Point(**args)  # type: ignore[arg-type]
    assert e.value.field == field
    assert str(e.value).startswith(f"{field}: ") and words in str(e.value)
    assert isinstance(e.value, ValueError)


def test_point_decoding_uses_the_data_helpers() -> None:
    block = [65534, *encode_float32(1.5, "CDAB"), *encode_uint32(70000), *encode_string("AB", 2)]
    assert pt(0).decode(block, 0) == 0xFFFE
    assert pt(0, type="int16").decode(block, 0) == -2
    assert pt(0, type="int16", scale=0.5, offset=1).decode(block, 0) == 0.0
    assert pt(3, type="int16").decode(block, 0) == 1  # 70000 >> 16, positive
    assert pt(0, scale=2).decode(block, 0) == 2 * 0xFFFE
    assert pt(1, type="float32", order="CDAB").decode(block, 0) == 1.5
    assert pt(3, type="uint32").decode(block, 0) == 70000
    assert pt(5, type="string", count=2).decode(block, 0) == "AB"
    assert pt(103, type="uint32").decode(block, 100) == 70000  # block read from 100
    assert pt(0, table="coils").decode([False, True], 0) is False
    assert pt(1, table="coils").decode([False, True], 0) is True
    with pytest.raises(ValueError, match="outside the block"):
        pt(6, type="uint32").decode(block, 0)


def test_change_only_with_deadband() -> None:
    p = pt(0, deadband=0.5, scale=0.1)
    assert p.changed(None, 1.0)
    assert not p.changed(1.0, 1.4)
    assert p.changed(1.0, 1.6) and p.changed(1.0, 0.4)
    assert p.changed(1.0, math.nan) and not p.changed(math.nan, math.nan)
    q = pt(0)
    assert not q.changed(5, 5) and q.changed(5, 6)
    s = pt(0, type="string", count=1)
    assert s.changed("a", "b") and not s.changed("a", "a")


# -- coalescing ---------------------------------------------------------------------------


def test_gaps_merge_only_when_cheaper_than_a_second_request() -> None:
    # a second request costs t3.5 + 8 + 5 characters + turnaround (about 19 characters
    # at 19200 8E1) so a gap of up to 9 registers (18 characters) is worth reading
    blocks = plan([pt(0), pt(10)], WIRE)  # gap of 9 registers
    assert [(b.address, b.count) for b in blocks] == [(0, 11)]
    blocks = plan([pt(0), pt(20)], WIRE)  # gap of 19: two requests
    assert [(b.address, b.count) for b in blocks] == [(0, 1), (20, 1)]
    # the rule itself, as stated: merged cost <= the two apart
    a, b = plan([pt(0)], WIRE)[0], plan([pt(10)], WIRE)[0]
    merged = WIRE.read("holding", 11)
    assert merge_pays(WIRE, a, b) == (merged <= 2 * WIRE.read("holding", 1))


def test_max_gap_bounds_merging() -> None:
    blocks = plan([pt(0), pt(5)], WIRE, Limits(max_gap=3))
    assert [(b.address, b.count) for b in blocks] == [(0, 1), (5, 1)]
    blocks = plan([pt(0), pt(4)], WIRE, Limits(max_gap=3))
    assert [(b.address, b.count) for b in blocks] == [(0, 5)]


def test_contiguous_points_up_to_the_maximum_per_request() -> None:
    points = [pt(a) for a in range(300)]
    blocks = plan(points, WIRE)
    assert [(b.address, b.count) for b in blocks] == [(0, 125), (125, 125), (250, 50)]
    assert sum(len(b.points) for b in blocks) == 300
    coils = [pt(a, table="coils") for a in range(4500)]
    assert [b.count for b in plan(coils, WIRE)] == [2000, 2000, 500]


def test_device_maxima_bonfiglioli_and_weg() -> None:
    # Bonfiglioli: FC 03 reads one parameter per request
    blocks = plan([pt(a) for a in range(5)], WIRE, Limits(max_registers=1))
    assert [b.count for b in blocks] == [1] * 5
    # WEG: a 64-byte telegram: 5 + 2n <= 64 -> 29 registers
    assert Limits(max_adu=64).registers() == 29
    blocks = plan([pt(a) for a in range(60)], WIRE, Limits(max_adu=64))
    assert [b.count for b in blocks] == [29, 29, 2]
    assert all(response_size("holding", b.count) <= 64 for b in blocks)
    assert Limits(max_adu=64, max_registers=10).registers() == 10
    assert Limits(max_adu=64).bit_count() == 59 * 8
    with pytest.raises(ValueError, match="max_registers"):
        Limits(max_registers=126)


def test_multi_register_points_are_never_split() -> None:
    points = [pt(0, type="float32"), pt(2, "s", type="string", count=8), pt(120, type="uint32")]
    blocks = plan(points, WIRE, Limits(max_registers=10))
    assert [(b.address, b.count) for b in blocks] == [(0, 10), (120, 2)]
    blocks = plan(points, WIRE, Limits(max_registers=9))
    assert [(b.address, b.count) for b in blocks] == [(0, 2), (2, 8), (120, 2)]


def test_groups_by_slave_and_table() -> None:
    points = [pt(0), pt(1, slave=2), pt(2, table="input"), pt(3, "c", table="coils")]
    blocks = plan(points, WIRE)
    assert len(blocks) == 4
    assert {(b.slave, b.table) for b in blocks} == {
        (1, "holding"), (2, "holding"), (1, "input"), (1, "coils")
    }  # fmt: skip


def test_mixed_intervals_share_a_request_only_when_cheaper() -> None:
    # neighbours: reading the slow one along with the fast one costs 2 characters a
    # read; a request of its own costs ~19 characters at its own (slow) rate
    fast, slow = pt(0, interval=0.1), pt(1, "slow", interval=1.0)
    assert len(plan([fast, slow], WIRE)) == 1
    # 100x slower and 9 registers away: its own request every 10 s is cheaper
    far = pt(10, "far", interval=10.0)
    blocks = plan([fast, far], WIRE)
    assert [(b.address, b.count, b.interval) for b in blocks] == [(0, 1, 0.1), (10, 1, 10.0)]
    # same distance and same interval: merged (the gap rule)
    assert len(plan([fast, pt(10, "near", interval=0.1)], WIRE)) == 1
    merged = plan([fast, slow], WIRE)[0]
    assert merged.interval == 0.1


def test_learned_cuts_and_split() -> None:
    points = [pt(a) for a in (0, 1, 2, 6, 7, 8)]
    blocks = plan(points, WIRE)
    assert [(b.address, b.count) for b in blocks] == [(0, 9)]
    lo, hi = split(blocks[0]) or (None, None)
    assert lo is not None and hi is not None
    assert (lo.address, lo.count, hi.address, hi.count) == (0, 3, 6, 3)
    cuts = Cuts()
    cuts.add("b", 1, "holding", hi.address)
    assert [(b.address, b.count) for b in plan(points, WIRE, cuts=cuts)] == [(0, 3), (6, 3)]
    # a cut only separates blocks that would read across it
    assert len(plan([pt(6), pt(7)], WIRE, cuts=cuts)) == 1
    assert split(plan([pt(3)], WIRE)[0]) is None


def test_chunks_for_on_demand_reads() -> None:
    assert chunks("holding", 10, 300, Limits()) == [(10, 125), (135, 125), (260, 50)]
    assert chunks("holding", 0, 3, Limits(max_registers=1)) == [(0, 1), (1, 1), (2, 1)]


def test_wire_prices_ascii_and_broadcast() -> None:
    w = Wire(10 / 9600, 0.0, 0.001, ascii=True)
    # ':' + 2 x (6 PDU+address bytes + LRC) + CR LF = 17 characters for a read request
    assert w.chars(8) == 17
    rtu = Wire(10 / 9600, 0.004, 0.001)
    assert rtu.frames(8, 0) == pytest.approx(0.004 + 8 * 10 / 9600)


def test_encode_point_undoes_scale_and_offset() -> None:
    from pyrtu.poller import encode_point

    assert encode_point(pt(0, scale=0.1), 30.0) == [300]
    assert encode_point(pt(0, type="int16", offset=-40), -50) == [0xFFF6]
    assert encode_point(pt(0, type="float32", order="CDAB"), 1.5) == encode_float32(1.5, "CDAB")
    assert encode_point(pt(0, type="uint32"), 70000) == encode_uint32(70000)
    assert encode_point(pt(0, type="string", count=2), "AB") == encode_string("AB", 2)
    assert encode_point(pt(0, table="coils"), True) == [True]
    p = pt(0, type="uint32", order="DCBA")
    assert p.decode(encode_point(p, 123456), 0) == 123456
    with pytest.raises(ValueError, match=r"outside 0\.\.65535"):
        encode_point(pt(0), 70000)
    with pytest.raises(ValueError, match="read only"):
        encode_point(pt(0, table="input"), 1)
    with pytest.raises(ValueError, match="finite number"):
        encode_point(pt(0), "x")
    with pytest.raises(ValueError, match="bool"):
        encode_point(pt(0, table="coils"), 2)


def test_encode_point_refuses_what_an_integer_register_cannot_hold() -> None:
    """One rule for every writer: an unscaled integer point takes whole numbers
    only (never rounded, banker's or otherwise); a scaled one rounds to its
    resolution, half away from zero, and says so; the range ends exactly."""
    from pyrtu.poller import encode_point

    plain = pt(0)
    assert encode_point(plain, 65535) == [65535] and encode_point(plain, 7.0) == [7]
    for bad in (0.5, 1.5, 2.5, 65534.5):
        with pytest.raises(ValueError, match="not a whole number"):
            encode_point(plain, bad)
    with pytest.raises(ValueError, match=r"outside 0\.\.65535"):
        encode_point(plain, 65536)
    with pytest.raises(ValueError, match=r"outside 0\.\.65535"):
        encode_point(plain, -1)
    kelvin = pt(0, type="int16", offset=273.15)  # whole steps of 1 from 273.15
    assert encode_point(kelvin, 294.15) == [21]
    with pytest.raises(ValueError, match=r"minus the offset 273\.15 is not a whole number"):
        encode_point(kelvin, 294.0)
    tenths = pt(0, scale=0.1)
    assert encode_point(tenths, 6553.5) == [65535] == encode_point(tenths, 6553.54)
    with pytest.raises(ValueError, match=r"outside 0\.\.65535"):
        encode_point(tenths, 6553.55)  # raw 65535.5 rounds up to 65536
    assert encode_point(tenths, 0.05) == [1]  # half away from zero
    assert encode_point(tenths, 0.04) == [0]


def test_encode_point_value_says_what_the_registers_hold() -> None:
    from pyrtu.poller.points import encode_point_value

    assert encode_point_value(pt(0), 7.0).value == 7 and not encode_point_value(pt(0), 7).rounded
    tenths = pt(0, scale=0.1)
    got = encode_point_value(tenths, 6553.5)
    assert got.words == [65535] and not got.rounded and got.value == 6553.5
    got = encode_point_value(tenths, 21.43)
    assert got.words == [214] and got.rounded and got.value == 21.4


# -- points sharing registers -----------------------------------------------------------


def _placed(blocks: list[Block], names: set[str]) -> None:
    """Every point named is in exactly one block, and that block reads all its registers."""
    seen = [p.name for b in blocks for p in b.points]
    assert sorted(seen) == sorted(names), seen
    for b in blocks:
        for p in b.points:
            assert b.address <= p.address and p.end <= b.end, (b, p)


@pytest.mark.parametrize("n", [2, 3])
def test_points_declared_on_one_address_are_all_read(n: int) -> None:
    """Two or three views of one register (raw, scaled, signed): one block, one
    register, every point in it (none dropped for sharing the previous one's address)."""
    views = [pt(7, "raw"), pt(7, "scaled", scale=0.1), pt(7, "signed", type="int16")][:n]
    blocks = plan(views, WIRE)
    assert [(b.address, b.count) for b in blocks] == [(7, 1)]
    _placed(blocks, {p.name for p in views})
    # beside other points, and with a device that reads one register per request
    more = [pt(6), *views, pt(8)]
    _placed(plan(more, WIRE), {p.name for p in more})
    one = plan(more, WIRE, Limits(max_registers=1))
    assert [(b.address, b.count) for b in one] == [(6, 1), (7, 1), (8, 1)]
    _placed(one, {p.name for p in more})


def test_overlapping_32_bit_points_are_all_read() -> None:
    """uint32 at 10 (10, 11) and float32 at 11 (11, 12), and a uint16 at 11: one block
    10..12; with two registers per request the float cannot join the first block."""
    points = [pt(10, "a", type="uint32"), pt(11, "b", type="float32"), pt(11, "c")]
    blocks = plan(points, WIRE)
    assert [(b.address, b.count) for b in blocks] == [(10, 3)]
    _placed(blocks, {"a", "b", "c"})
    two = plan(points, WIRE, Limits(max_registers=2))
    _placed(two, {"a", "b", "c"})
    assert all(b.count <= 2 for b in two)
    # the block's registers decode each point (struct: big-endian words, ABCD)
    regs = [0x0001, 0x3FC0, 0x0000]  # 10..12: a = 0x00013FC0, b = 1.5 (0x3FC00000)
    by_name = {p.name: p for p in points}
    assert by_name["a"].decode(regs, 10) == 0x00013FC0
    assert by_name["b"].decode(regs, 10) == 1.5
    assert by_name["c"].decode(regs, 10) == 0x3FC0


def test_a_change_of_exactly_the_deadband_is_not_delivered() -> None:
    """docs/POLLER.md: a value is delivered when it differs from the last delivered one
    by *more than* the deadband: exactly the deadband is not enough (values exact in
    binary, so the difference is exactly the deadband)."""
    p = pt(0, deadband=0.5, type="float32")
    assert not p.changed(1.0, 1.5) and not p.changed(1.5, 1.0)
    assert p.changed(1.0, 1.5 + 2**-20) and p.changed(1.0, 0.5 - 2**-20)
    q = pt(0, deadband=2)  # integers: 10 -> 12 is exactly the deadband
    assert not q.changed(10, 12) and not q.changed(12, 10) and q.changed(10, 13)
