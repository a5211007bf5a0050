"""The set commands' rules that the mutation run (docs/MUTATION.md) found untested:
the payload limit at its boundary, the first unknown key named, 0 and 1 as a
bool's values, the token bucket's wait and its burst, the ids remembered (the last
4096, docs/BRIDGE.md), a result for an id no longer remembered."""

from __future__ import annotations

import json
import math

import pytest

from pyrtu.bridge.commands import (
    CommandQueue,
    Refusal,
    SetCommand,
    TokenBucket,
    check_value,
    parse,
    result,
)
from pyrtu.poller import Point

REF = Point("d.ref", "line", 1, "holding", 683, type="int16")
FLAG = Point("d.flag", "line", 1, "coils", 0)


def test_a_payload_of_exactly_the_limit_is_taken() -> None:
    assert parse(b"1" * 64, max_payload=64, retained=False) == (int("1" * 64), None, None)
    refused = parse(b"1" * 65, max_payload=64, retained=False)
    assert isinstance(refused, Refusal) and refused.error == "too_large"


def test_the_first_unknown_key_in_order_is_named() -> None:
    got = parse(b'{"value": 1, "zz": 0, "aa": 0}', max_payload=64, retained=False)
    assert isinstance(got, Refusal) and got.error == "malformed"
    assert got.message == "unknown key 'aa' (keys: value, id, time)"


@pytest.mark.parametrize(("value", "want"), [(0, False), (1, True), (True, True), (False, False)])
def test_a_bool_takes_0_and_1(value: object, want: bool) -> None:
    assert check_value(FLAG, value).value is want


@pytest.mark.parametrize("value", [-1, 2])
def test_a_bool_refuses_other_integers(value: int) -> None:
    with pytest.raises(ValueError, match="true or false"):
        check_value(FLAG, value)


def test_the_wait_is_the_time_to_the_next_whole_token() -> None:
    bucket = TokenBucket(rate=2.0, burst=1.0, now=0.0)
    assert bucket.wait(0.0) == 0.0
    # half a token came in 0.25 s at 2 a second: the other half takes 0.25 s more
    assert bucket.wait(0.25) == pytest.approx(0.25)
    assert bucket.wait(0.4) == pytest.approx(0.1)


@pytest.mark.parametrize(("rate", "burst"), [(0.5, 1), (2.0, 2), (3.0, 3), (10.0, 4)])
def test_a_slaves_burst_is_its_rate_between_1_and_4(rate: float, burst: int) -> None:
    bucket = CommandQueue(size=8, rate=rate).bucket(("line", 1), 100.0)
    waits = [bucket.wait(100.0) for _ in range(burst + 1)]
    assert waits[:burst] == [0.0] * burst
    assert waits[burst] == pytest.approx(1 / rate)


def _command(cid: str) -> SetCommand:
    return SetCommand(REF, 1, cid, 10.0, 0.0, "r")


def test_the_last_4096_ids_are_remembered() -> None:
    q = CommandQueue(size=10_000, rate=1.0)
    for i in range(4096):
        assert q.push(_command(f"id{i}"))
    assert q.known("id0") == (True, None)  # (it moves to the end: the newest)
    q.push(_command("id4096"))
    assert q.known("id1") == (False, None)  # the oldest, forgotten
    assert q.known("id0") == (True, None)
    assert len(q.seen) == 4096


def test_a_result_for_an_id_no_longer_remembered_is_not_kept() -> None:
    q = CommandQueue(size=8, rate=1.0)
    q.done("gone", b"result")
    assert q.known("gone") == (False, None) and "gone" not in q.seen


def test_a_results_fields_are_keywords_only() -> None:
    from pyrtu.bridge.commands import result

    with pytest.raises(TypeError):
        result("p", True, "id")  # type: ignore[misc]


def test_a_refusal_is_immutable_and_hashable() -> None:
    import dataclasses

    refusal = Refusal("busy", "queue full", "x")
    assert hash(refusal) == hash(Refusal("busy", "queue full", "x"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        refusal.error = "other"  # type: ignore[misc]


def test_a_new_queue_counts_nothing() -> None:
    q = CommandQueue(size=8, rate=1.0)
    assert (q.waiting, q.refused, q.expired, q.executed, q.duplicates) == (0, 0, 0, 0, 0)


@pytest.mark.parametrize("value", [True, False, 1.0, None])
def test_an_enum_takes_a_label_or_its_number_only(value: object) -> None:
    mode = Point("d.mode", "line", 1, "holding", 0, enum=["off", "heat"], writable=True)
    assert check_value(mode, "heat").words == [1] and check_value(mode, 0).words == [0]
    with pytest.raises(ValueError, match=r'value must be one of "off", "heat"'):
        check_value(mode, value)


#: a point with a range, as docs/BRIDGE.md's `min`/`max` keys give it: both ends taken
RANGED = Point("d.speed", "line", 1, "holding", 100, type="int16", min=-50, max=1500)


@pytest.mark.parametrize("value", [-50, 1500, -50.0, 1500.0])
def test_a_value_exactly_at_min_or_max_is_taken(value: float) -> None:
    assert check_value(RANGED, value).value == value


@pytest.mark.parametrize(("value", "word"), [(-51, "below"), (1501, "above"), (1500.5, "above")])
def test_a_value_just_outside_min_or_max_is_refused(value: float, word: str) -> None:
    with pytest.raises(ValueError, match=word):
        check_value(RANGED, value)


def test_the_payload_limit_and_retained_flag_are_keywords_only() -> None:
    with pytest.raises(TypeError):
        parse(b"1", 64, False)  # type: ignore[misc]


def _strict_json(data: bytes) -> object:
    """JSON as RFC 8259 has it: NaN and Infinity are not values."""

    def refuse(name: str) -> object:
        raise AssertionError(f"{name} in {data!r}: not JSON")

    return json.loads(data, parse_constant=refuse)


@pytest.mark.parametrize("read_back", [math.nan, math.inf, -math.inf])
def test_a_write_whose_read_back_is_not_a_number_is_ok_with_a_null_value(
    read_back: float,
) -> None:
    """The write was answered, the read-back of a float point is NaN or infinite (a
    device's own not-a-number): the result is ok, its value null, as the point's
    topic publishes it (it raised, and the write was reported failed)."""
    doc = _strict_json(result("d.temp", True, id="7", value=read_back, time=1.5))
    assert doc == {"ok": True, "point": "d.temp", "id": "7", "value": None, "time": 1.5}


def test_a_results_numbers_are_kept() -> None:
    doc = _strict_json(result("d.temp", True, value=21.5, time=2.0))
    assert doc == {"ok": True, "point": "d.temp", "value": 21.5, "time": 2.0}
