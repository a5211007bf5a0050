"""The C core's own API on the inputs the fuzzer (fuzz/) found mishandled.

Each test failed before its fix (issue 9, "From the fuzzer"): rtu_parse looping
with a capacity of one event, rtu_parser_init accepting char_us == 0,
rtu_rules_set accepting a count rule shorter than any ADU, rtu_predict reading
out of bounds for a bad direction, and int64 time arithmetic that wrapped.
"""

from __future__ import annotations

from typing import Any

import pytest
from c_core import needs_c

import pyrtu

pytestmark = needs_c("c" not in pyrtu.available_backends())


@pytest.fixture
def core() -> tuple[Any, Any]:
    from pyrtu.core._rtu_core import ffi, lib

    return ffi, lib


def _config(core: tuple[Any, Any], strict: int = 0) -> Any:
    ffi, lib = core
    cfg = ffi.new("rtu_config *")
    assert lib.rtu_config_init(cfg, 2, 19200, 11, 0) == lib.RTU_OK
    cfg.strict = strict
    return cfg


def _events(out: Any, n: int) -> list[tuple[int, int, int, int]]:
    return [(out[i].offset, out[i].length, out[i].kind, out[i].error) for i in range(n)]


def _parse(core: tuple[Any, Any], data: bytes, cap: int) -> tuple[list[Any], int]:
    """All events of data, `cap` at a time; returns them and the number of calls."""
    ffi, lib = core
    cfg = _config(core)
    parser = ffi.new("rtu_parser *")
    assert lib.rtu_parser_init(parser, cfg) == lib.RTU_OK
    out = ffi.new("rtu_event[]", cap)
    n = ffi.new("size_t *")
    events: list[Any] = []
    for calls in range(1, 4 * len(data) + 4):
        st = lib.rtu_parse(parser, data, len(data), ffi.NULL, 0, ffi.NULL, ffi.NULL, 0, out, cap, n)
        events += _events(out, n[0])
        if st == lib.RTU_OK:
            return events, calls
        assert st == lib.RTU_ENOSPC
        assert n[0] >= 1, "RTU_ENOSPC without progress"
    pytest.fail(f"rtu_parse with capacity {cap} did not finish")


def test_parse_makes_progress_with_capacity_one(core: tuple[Any, Any]) -> None:
    # noise then a frame: a discard run and a frame need two slots at once
    frame = pyrtu.add_crc(bytes.fromhex("0103000a0002"))
    data = b"\xff\xfe" + frame + b"\x00" + frame
    whole, calls = _parse(core, data, 64)
    assert calls == 1 and [e[2] for e in whole] == [4, 0, 4, 0]
    for cap in (1, 2, 3):
        assert _parse(core, data, cap)[0] == whole


def test_parse_refuses_capacity_zero_with_work_left(core: tuple[Any, Any]) -> None:
    ffi, lib = core
    parser = ffi.new("rtu_parser *")
    lib.rtu_parser_init(parser, _config(core))
    n = ffi.new("size_t *", 7)
    st = lib.rtu_parse(parser, b"\x01\x02", 2, ffi.NULL, 0, ffi.NULL, ffi.NULL, 0, ffi.NULL, 0, n)
    assert st == lib.RTU_EINVAL and n[0] == 0
    # nothing to do: capacity 0 is fine
    st = lib.rtu_parse(parser, b"", 0, ffi.NULL, 0, ffi.NULL, ffi.NULL, 0, ffi.NULL, 0, n)
    assert st == lib.RTU_OK and n[0] == 0


@pytest.mark.parametrize(
    "field, value",
    [("char_us", 0), ("char_us", -1), ("t15_us", -1), ("t35_us", -5), ("max_adu", 3)],
)
def test_parser_init_checks_like_framer_init(core: tuple[Any, Any], field: str, value: int) -> None:
    ffi, lib = core
    cfg = _config(core)
    if field == "max_adu":
        cfg.max_adu = value
    else:
        setattr(cfg.timing, field, value)
    assert lib.rtu_framer_init(ffi.new("rtu_framer *"), cfg) == lib.RTU_EINVAL
    assert lib.rtu_parser_init(ffi.new("rtu_parser *"), cfg) == lib.RTU_EINVAL


def test_marks_from_chunks_refuses_char_us_zero(core: tuple[Any, Any]) -> None:
    ffi, lib = core
    timing = ffi.new("rtu_timing *", (0, 750, 1750))
    offsets = ffi.new("uint64_t[]", [0, 1])
    times = ffi.new("int64_t[]", [0, 10_000])
    marks = ffi.new("rtu_mark[]", 2)
    n = ffi.new("size_t *")
    assert lib.rtu_marks_from_chunks(timing, offsets, times, 2, 2, marks, n) == lib.RTU_EINVAL


@pytest.mark.parametrize(
    "rule, ok",
    [
        ((1, 0, 0, 0, 3), False),  # fixed 3 bytes: shorter than any ADU
        ((1, 0, 0, 0, 4), True),
        ((2, 2, 1, 1, 0), False),  # count at 2, nothing after: 3 bytes for count 0
        ((2, 2, 1, 1, 1), True),  # 4 bytes for count 0
        ((2, 2, 2, 1, 0), True),
        ((2, 255, 2, 1, 1000), False),  # shortest ADU 1257 bytes: past any max_adu
        ((2, 2, 1, 0, 2), False),  # scale 0
        ((2, 1, 1, 1, 2), False),  # count inside the function code
    ],
)
def test_rules_set_bounds_count_rules_like_fixed_ones(
    core: tuple[Any, Any], rule: tuple[int, ...], ok: bool
) -> None:
    ffi, lib = core
    cfg = _config(core)
    c_rule = ffi.new("rtu_rule *", rule)
    st = lib.rtu_rules_set(ffi.addressof(cfg, "rules"), 0, 100, c_rule[0])
    assert (st == lib.RTU_OK) is ok


@pytest.mark.parametrize("direction", [-1, 2, 1000, -(2**31)])
def test_predict_refuses_a_bad_direction(core: tuple[Any, Any], direction: int) -> None:
    ffi, lib = core
    cfg = _config(core)
    length = ffi.new("size_t *")
    adu = bytes.fromhex("0103000a0002c5cd")
    st = lib.rtu_predict(ffi.addressof(cfg, "rules"), direction, adu, len(adu), length)
    assert st == 2  # RTU_PRED_UNKNOWN (it indexed rule[direction] out of bounds)


INT64_MAX = 2**63 - 1


def _framer(core: tuple[Any, Any], cfg: Any) -> Any:
    ffi, lib = core
    f = ffi.new("rtu_framer *")
    assert lib.rtu_framer_init(f, cfg) == lib.RTU_OK
    return f


def _poll(core: tuple[Any, Any], f: Any) -> tuple[int, int, int, int]:
    _ffi, lib = core
    assert lib.rtu_framer_poll(f) == 1
    e = f.event
    return e.kind, e.length, e.start_us, e.end_us


FRAME = bytes.fromhex("0103000a0002") + b"\xe4\x09"  # FC 03 request, CRC low byte first


def test_framer_deadline_saturates_instead_of_wrapping(core: tuple[Any, Any]) -> None:
    _ffi, lib = core
    cfg = _config(core)
    char = cfg.timing.char_us
    f = _framer(core, cfg)
    assert lib.rtu_framer_feed(f, b"\x01\x03", 2, INT64_MAX - 10) == 2
    # the last arrival + t3.5 lies past INT64_MAX: no deadline, never one in the past
    assert lib.rtu_framer_deadline(f) == INT64_MAX
    lib.rtu_framer_handle_timer(f, -INT64_MAX)  # far in the past: no silence
    assert lib.rtu_framer_poll(f) == 0
    f = _framer(core, cfg)
    assert lib.rtu_framer_feed(f, FRAME, 8, INT64_MAX - 10) == 8
    assert _poll(core, f) == (0, 8, INT64_MAX - 10 - 8 * char, INT64_MAX - 10)
    # the most negative time after the most positive one: clamped to the last arrival
    assert lib.rtu_framer_feed(f, FRAME, 8, -(2**63)) == 8
    assert _poll(core, f) == (0, 8, INT64_MAX - 10 - char, INT64_MAX - 10)


def test_framer_spreads_a_huge_burst_without_overflow(core: tuple[Any, Any]) -> None:
    _ffi, lib = core
    cfg = _config(core)
    cfg.timing.char_us = 2**62
    cfg.timing.t15_us = cfg.timing.t35_us = 0
    f = _framer(core, cfg)
    assert lib.rtu_framer_feed(f, FRAME, 8, 0) == 8
    # byte 0 would arrive at -7 * 2**62: saturated, never wrapped to a positive time
    assert _poll(core, f) == (0, 8, -INT64_MAX, 0)


def test_stream_times_saturate(core: tuple[Any, Any]) -> None:
    ffi, lib = core
    cfg = _config(core)
    parser = ffi.new("rtu_parser *")
    lib.rtu_parser_init(parser, cfg)
    frame = pyrtu.add_crc(bytes.fromhex("0103000a0002"))
    offsets = ffi.new("uint64_t[]", [0, 4])
    times = ffi.new("int64_t[]", [INT64_MAX, -(2**63)])
    marks = ffi.new("rtu_mark[]", 2)
    nm = ffi.new("size_t *")
    assert (
        lib.rtu_marks_from_chunks(
            ffi.addressof(cfg, "timing"), offsets, times, 2, len(frame), marks, nm
        )
        == lib.RTU_OK
    )
    assert nm[0] == 0  # the second chunk is clamped to the first: no silence
    out = ffi.new("rtu_event[]", 4)
    n = ffi.new("size_t *")
    st = lib.rtu_parse(parser, frame, len(frame), marks, 0, offsets, times, 2, out, 4, n)
    assert st == lib.RTU_OK and n[0] == 1
    assert out[0].start_us == INT64_MAX - 3 * cfg.timing.char_us - cfg.timing.char_us
    assert out[0].end_us == INT64_MAX  # never RTU_NO_TIME (INT64_MIN)
