"""The gateway's liveness rules without sockets (pyrtu.gateway._live): the count of
requests waiting, and which connection a newcomer replaces in a full table (the
module docstring: the oldest that never completed a request, else the longest
idle; never one with work in progress)."""

from __future__ import annotations

import pytest

from pyrtu.gateway._live import IDLE, Liveness, pick_victim


def test_each_answer_takes_one_request_off_the_waiting_count() -> None:
    live = Liveness(connected=0.0)
    live.data(1.0, partial=False, completed=True)
    live.outstanding += 2  # two requests queued for the bus
    live.answered(2.0)
    assert live.outstanding == 1
    assert live.expired(1000.0, 5.0, 120.0) is None  # one still waits: never idle
    live.answered(3.0)
    assert live.outstanding == 0 and live.last_active == 3.0
    assert live.expired(122.9, 5.0, 120.0) is None
    assert live.expired(123.0, 5.0, 120.0) == IDLE


def test_a_typo_in_a_liveness_field_is_an_error_not_a_new_attribute() -> None:
    live = Liveness(connected=0.0)
    with pytest.raises(AttributeError):
        live.outstandng = 1  # type: ignore[attr-defined]


def test_the_busy_are_skipped_not_the_end_of_the_search() -> None:
    busy = Liveness(connected=0.0, outstanding=1)
    silent = Liveness(connected=5.0)
    idle = Liveness(connected=0.0, last_active=1.0)
    assert pick_victim([(1, busy, False), (2, silent, False)]) == 2
    assert pick_victim([(1, Liveness(connected=0.0), True), (2, idle, False)]) == 2
    assert pick_victim([(1, busy, False), (2, idle, True), (3, idle, False)]) == 3


def test_one_that_never_talked_goes_before_any_that_did() -> None:
    """Rank before time: a connection that never completed a request is evicted
    before one that did, even when the talker has been silent for longer."""
    never = Liveness(connected=50.0)  # connected at 50, not a request since
    talked_long_ago = Liveness(connected=0.0, last_active=10.0)
    assert pick_victim([(1, talked_long_ago, False), (2, never, False)]) == 2
    assert pick_victim([(2, never, False), (1, talked_long_ago, False)]) == 2
    # among those that talked, the longest idle; among the silent, the oldest
    recent = Liveness(connected=0.0, last_active=40.0)
    assert pick_victim([(1, recent, False), (2, talked_long_ago, False)]) == 2
    newer = Liveness(connected=60.0)
    assert pick_victim([(1, newer, False), (2, never, False)]) == 2
