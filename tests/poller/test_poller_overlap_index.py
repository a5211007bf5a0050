"""The overlap check of a configuration's points (`pyrtu.poller.points.RegisterIndex`):
which earlier points share a register with a new one, found by address rather than by
comparing every pair.  Judged against the plain definition (two register ranges
[a, a+n) and [b, b+m) share a register when a < b+m and b < a+n)."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from pyrtu.poller import ConfigError, Point, make_config
from pyrtu.poller.config import Bus
from pyrtu.poller.points import RegisterIndex

#: register widths of the types (struct sizes / 2), independent of the codec table
WIDTH = {"uint16": 1, "uint32": 2, "float64": 4}


def point(rank: int, address: int, type_: str) -> Point:
    return Point(f"p{rank}", "b", 1, "holding", address, type_)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 40), st.sampled_from(sorted(WIDTH))), min_size=1, max_size=25)
)
def test_the_index_finds_exactly_the_points_that_share_a_register(
    specs: list[tuple[int, str]],
) -> None:
    index = RegisterIndex()
    placed: list[tuple[int, int, int]] = []  # (rank, start, end) by the definition
    for rank, (address, type_) in enumerate(specs):
        p = point(rank, address, type_)
        end = address + WIDTH[type_]
        want = [r for r, a, e in placed if a < end and address < e]
        assert [r for r, _ in index.overlapping(p)] == want  # in the order noted
        index.add(rank, p)
        placed.append((rank, address, end))


def test_a_wide_point_far_before_is_found_at_its_last_register() -> None:
    index = RegisterIndex()
    index.add(0, point(0, 100, "float64"))  # registers 100..103
    index.add(1, point(1, 0, "uint16"))
    assert [r for r, _ in index.overlapping(point(2, 103, "uint16"))] == [0]
    assert index.overlapping(point(3, 104, "uint16")) == []  # the register after it
    assert index.overlapping(point(4, 99, "uint16")) == []  # the register before it
    assert [r for r, _ in index.overlapping(point(5, 99, "uint32"))] == [0]


def test_a_config_names_the_first_point_that_overlaps_and_the_earliest_it_overlaps() -> None:
    bus = Bus("b", "loop://")
    points = [
        Point("wide", "b", 1, "holding", 10, "float64"),  # 10..13
        Point("a", "b", 1, "holding", 0, "uint16"),
        Point("x", "b", 1, "holding", 12, "uint32"),  # 12..13: overlaps "wide"
        Point("y", "b", 1, "holding", 13, "uint16"),  # overlaps both, comes later
    ]
    try:
        make_config([bus], points)
    except ConfigError as e:
        text = str(e)
    else:
        raise AssertionError("an overlap was accepted")
    assert 'point[2] ("x")' in text and "'wide'" in text


def test_thousands_of_points_of_one_slave_load() -> None:
    """Ten thousand adjacent registers of one slave: each checked against its
    neighbours only (the check was quadratic: 50 million comparisons here)."""
    bus = Bus("b", "loop://")
    points = [Point(f"r{i}", "b", 1, "holding", i % 60000, "uint16") for i in range(10000)]
    cfg = make_config([bus], points)
    assert len(cfg.points) == 10000
