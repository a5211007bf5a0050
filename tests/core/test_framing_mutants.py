"""The twin's length prediction (pyrtu/core/_pure/predict.py) where the mutation run
(docs/MUTATION.md) found it untested: one byte cannot decide (the function code is
the second), and a Read Device Identification answer (Application Protocol V1.1b
6.21) whose objects run past the 1024-byte limit gets its length at once."""

from __future__ import annotations

from pyrtu.core._pure.predict import (
    DIR_REQUEST,
    DIR_RESPONSE,
    PRED_LENGTH,
    PRED_NEED,
    make_rules,
    predict,
)

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
