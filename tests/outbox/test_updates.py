"""Point updates as outbox records (pyrtu.outbox.updates): the layout written out
here from the module's docstring, round trips through a real outbox, refusals."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from pyrtu.outbox.outbox import Outbox
from pyrtu.outbox.updates import PointUpdate, UpdateError, decode_update, encode_update, is_update


def test_the_record_is_the_mark_and_a_json_array() -> None:
    rec = encode_update(PointUpdate("speed", 12.5, 1700000000.25, "good"))
    assert rec[:4] == b"\x00pu1"
    assert json.loads(rec[4:]) == ["speed", 12.5, 1700000000.25, "good"]


@pytest.mark.parametrize(
    "value", [True, False, 0, -(2**63), 2**64 - 1, 1.5, -0.0, "text é", None, math.inf]
)
def test_every_value_type_round_trips_through_an_outbox(tmp_path: Path, value: object) -> None:
    update = PointUpdate("p", value, None if value is None else 1.0, "stale")  # type: ignore[arg-type]
    with Outbox(tmp_path / "ob") as box:
        box.append(encode_update(update), 0.0)
        box.flush()
    with Outbox(tmp_path / "ob") as box:
        [(_, rec)] = box.pending(10)
    got = decode_update(rec)
    assert got == update and type(got.value) is type(value)


def test_nan_round_trips() -> None:
    got = decode_update(encode_update(PointUpdate("p", math.nan, 2.0, "good")))
    assert isinstance(got.value, float) and math.isnan(got.value)


def test_a_record_of_an_earlier_json_bridge_is_no_update() -> None:
    """The JSON bridge of earlier pyrtus stored a topic, a newline and a payload:
    told apart by the leading mark (no topic begins with a NUL)."""
    assert not is_update(b'a/b/c\n{"value":1')
    assert is_update(encode_update(PointUpdate("p", 1, 1.0, "good")))
    with pytest.raises(UpdateError, match="no leading mark"):
        decode_update(b'a/b/c\n{"value":1')


@pytest.mark.parametrize(
    "body",
    [
        b"[",
        b'["p",1,1.0]',
        b'[1,1,1.0,"good"]',
        b'["p",1,1.0,"fine"]',
        b'["p",[1],1.0,"good"]',
        b'["p",1,"t","good"]',
        b'["p",1,true,"good"]',
        b"\xff",
    ],
)
def test_a_damaged_record_is_refused(body: bytes) -> None:
    with pytest.raises(UpdateError):
        decode_update(b"\x00pu1" + body)


def test_an_unknown_quality_is_refused_when_encoding() -> None:
    with pytest.raises(ValueError, match="quality must be one of good, stale, bad"):
        encode_update(PointUpdate("p", 1, 1.0, "fine"))


def test_text_is_stored_as_utf_8_not_escaped() -> None:
    """A name or a string value outside ASCII is stored as its UTF-8 bytes (the record
    as long as the text), not as \\u escapes."""
    rec = encode_update(PointUpdate("température", "état é", 1.0, "good"))
    assert rec == b"\x00pu1" + '["température","état é",1.0,"good"]'.encode()
    assert decode_update(rec).value == "état é"


@pytest.mark.parametrize("time", [b"Infinity", b"-Infinity", b"NaN"])
def test_a_time_that_is_no_finite_number_is_refused(time: bytes) -> None:
    with pytest.raises(UpdateError, match="bad time"):
        decode_update(b'\x00pu1["p",1,' + time + b',"good"]')


def test_a_point_update_is_immutable_and_hashable() -> None:
    """A value read at a time: equal updates are one (a set holds it once) and none
    changes after it is made (it may sit in an outbox or a queue meanwhile)."""
    update = PointUpdate("d.speed", 1500, 10.5, "good")
    assert {update, PointUpdate("d.speed", 1500, 10.5, "good")} == {update}
    with pytest.raises(AttributeError):
        update.value = 0  # type: ignore[misc]
