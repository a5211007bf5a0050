"""The twin's framing where the mutation run (docs/MUTATION.md) found it untested:
one byte cannot decide the length (the function code is the second), a Read Device
Identification answer (Application Protocol V1.1b 6.21) whose objects run past the
1024-byte limit gets its length at once, and the bytes still needed when the head
itself bounds nothing but a frame begins after a t3.5 silence behind it."""

from __future__ import annotations

from types import ModuleType

from pyrtu.core._pure.predict import (
    DIR_REQUEST,
    DIR_RESPONSE,
    PRED_LENGTH,
    PRED_NEED,
    make_rules,
    predict,
)
from pyrtu.core.rules import LengthRule

RULES = make_rules({})


def test_one_byte_needs_the_function_code() -> None:
    for direction in (DIR_REQUEST, DIR_RESPONSE):
        assert predict(RULES, direction, b"\x01", 1) == (PRED_NEED, 2)


def test_a_device_id_answer_past_the_limit_has_its_length_at_once() -> None:
    # address, 0x2B, MEI 0x0E, read code 1, conformity 1, more 0, next 0, 5 objects;
    # each object: id, length 255, 255 bytes: past 1024 after the fourth
    head = bytes((1, 0x2B, 0x0E, 1, 1, 0, 0, 5))
    objects = b"".join(bytes((i, 255)) + bytes(255) for i in range(4))
    adu = head + objects
    assert predict(RULES, DIR_RESPONSE, adu, len(adu)) == (PRED_LENGTH, 8 + 4 * 257 + 2)


def test_a_frame_after_a_silence_bounds_the_wait_when_the_head_bounds_nothing(
    backend: ModuleType,
) -> None:
    """A head whose shortest frame is past max_adu bounds nothing (0), yet it waits in
    lenient mode (its count byte is not in); a frame that begins after a t3.5 silence
    behind it may end first, so its need is the bound: "01 03" is a read request
    (8 bytes, [AP] 6.3) or another slave's answer (at least 5: count 0), 3 more."""
    # vendor function 0x41: count at offset 2, then 300 bytes: past max_adu (256)
    rules = {0x41: (LengthRule.counted(2, 1, 1, 300), None)}
    f = backend.Framer("slave", baudrate=9600, rules=rules)
    f.receive_data(b"\x01\x41", 1.0)
    assert f.next_event() is None
    assert f.needed() == 0  # the head's own bound: none
    f.receive_data(b"\x01\x03", 1.010)  # 10 ms later: past t3.5 (4 ms), short of 50
    assert f.next_event() is None
    assert f.needed() == 5 - 2
