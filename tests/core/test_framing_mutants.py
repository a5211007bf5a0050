"""The twin's framing where the mutation run (docs/MUTATION.md) found it untested:
one byte cannot decide the length (the function code is the second), a Read Device
Identification answer (Application Protocol V1.1b 6.21) whose objects run past the
1024-byte limit gets its length at once, and the bytes still needed when the head
itself bounds nothing but a frame begins after a t3.5 silence behind it."""

from __future__ import annotations

import signal
from types import ModuleType
from typing import Any

import pytest
from vectors import crc_bitwise

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
MAX_RTU_ADU = 256  # [SL] 2.5.1: the longest RTU frame, the framer's default max_adu


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


def test_an_unknown_frame_after_a_silence_leaves_the_heads_bound(backend: ModuleType) -> None:
    """The head "01 10" (Write Multiple registers, [AP] 6.12: 9 bytes at least, or
    another slave's 8-byte answer) needs 6 more; after a t3.5 silence come two bytes
    of a frame with no length rule (0x5A): it bounds nothing, and the head's own
    bound stands (8 - 4 bytes: the two count towards the head too)."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x10", 1.0)
    assert f.next_event() is None
    assert f.needed() == 8 - 2
    f.receive_data(b"\x01\x5a", 1.010)  # 10 ms later: past t3.5 (4 ms), short of 50
    assert f.next_event() is None
    assert f.needed() == 8 - 4


def test_a_deadline_past_the_int64_range_is_no_timer(backend: ModuleType) -> None:
    """Times are int64 microseconds that saturate, as in the C core (csrc/rtu_internal.h):
    bytes at the last representable millisecond, their t3.5 lies past 2**63 - 1 us,
    so there is no timer (never a deadline in the past, nor one beyond the range)."""
    f = backend.Framer("slave", baudrate=9600)
    last = (2**63 - 1) / 1e6 - 0.001  # 1 ms before the end: t3.5 (4 ms) runs past it
    f.receive_data(b"\x01\x03", last)
    assert f.next_event() is None
    assert f.timer() is None


def test_a_monitor_calls_a_silence_framed_mei_frame_a_request(backend: ModuleType) -> None:
    """Function 43 is a request ([AP] 6.19-6.21); MEI type 13 (CANopen General
    Reference) has no length rule, so the frame ends by its silence: a monitor
    that awaits no answer calls it a request (the function has a request rule),
    not unknown."""
    f = backend.Framer("monitor", baudrate=9600)
    adu = bytes(backend.add_crc(b"\x01\x2b\x0d\x00\x01\x02"))
    f.receive_data(adu, 1.0)
    f.handle_timer(1.1)
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu
    assert str(ev.kind) == "request"


def test_a_device_id_answer_exactly_at_the_limit_walks_on() -> None:
    """Read Device Identification answer ([AP] 6.21): 8 bytes, then objects (id, length,
    value).  Three of 255 bytes and one of 243 bring it to exactly 1024 bytes, not
    past the limit: the walk goes on to the fifth object (1 byte): 1027, with the
    CRC 1029."""
    head = bytes((1, 0x2B, 0x0E, 1, 1, 0, 0, 5))
    objects = b"".join(bytes((i, 255)) + bytes(255) for i in range(3))
    objects += bytes((3, 243)) + bytes(243) + bytes((4, 1, 0))
    adu = head + objects
    assert len(head + objects[:-3]) == 1024
    assert predict(RULES, DIR_RESPONSE, adu, len(adu)) == (PRED_LENGTH, 1027 + 2)


def test_a_complete_length_with_a_wrong_crc_does_not_end_the_wait(backend: ModuleType) -> None:
    """Eight bytes "01 03 10 00 ...": as a read request (8 bytes, [AP] 6.3) they are
    all in but their CRC is wrong; as another slave's answer its count says 16 data
    bytes, 5 + 16 = 21 in all: 13 more are needed, not 0."""
    f = backend.Framer("slave", baudrate=9600)
    head = b"\x01\x03\x10" + bytes(5)
    assert bytes(backend.add_crc(head[:6]))[6:] != head[6:]  # not a request
    f.receive_data(head, 1.0)
    assert f.next_event() is None
    assert f.needed() == 21 - 8


def test_the_bound_looks_through_two_silences(backend: ModuleType) -> None:
    """An answer that claims 255 data bytes (5 + 255 = 260, kept in lenient mode with
    max_adu 1024), a t3.5 silence, two bytes of a frame with no length rule (0x5A),
    another silence, then "01 03": the start of an answer of 5 bytes at least.  The
    frame after the second silence may end first: 3 more, not the first's 253."""
    f = backend.Framer("master", baudrate=9600, max_adu=1024)
    f.receive_data(b"\x01\x03\xff", 1.0)
    assert f.needed() == 260 - 3
    f.receive_data(b"\x01\x5a", 1.010)  # each 10 ms later: past t3.5 (4 ms), short of 50
    assert f.needed() == 260 - 5
    f.receive_data(b"\x01\x03", 1.020)
    assert f.next_event() is None
    assert f.needed() == 5 - 2


def test_a_gap_shorter_than_t35_begins_no_frame(backend: ModuleType) -> None:
    """Lenient mode: "01 10" waits for its count byte; a read request follows after
    2.5 characters of silence (above t1.5, below t3.5: [SL] 2.5.1.1 begins a frame
    only after t3.5).  Nothing is framed until the silence after it; then the two
    bytes go (their CRC fails wherever they end) and the request is framed."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x10", 1.0)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    end = 1.0 + (2.5 + len(request)) * char
    f.receive_data(request, end)
    assert f.next_event() is None
    f.handle_timer(end + 0.1)
    events = [(str(ev.kind), ev.adu) for ev in f.events()]
    assert events == [("discard", b"\x01\x10"), ("request", request)]


def test_strict_a_gap_after_the_first_byte_discards_the_frame(backend: ModuleType) -> None:
    """Strict mode, [SL] 2.5.1.1: a silence of more than t1.5 between two characters
    makes the frame incomplete, to be discarded, even right after its first byte
    (2.5 characters here, below t3.5: no new frame)."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600, strict=True)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(request[:1], 1.0)
    end = 1.0 + (2.5 + len(request) - 1) * char
    f.receive_data(request[1:], end)
    f.handle_timer(end + 0.1)
    events = [(str(ev.kind), ev.error, ev.adu) for ev in f.events()]
    assert events == [("discard", "t1.5", request)]


def test_a_frame_after_a_short_gap_and_a_silence_is_found_at_once(backend: ModuleType) -> None:
    """Lenient mode: "01 10" waits for its count byte; 2.5 characters later (a gap,
    no frame start) comes one stray byte, then after a t3.5 silence a whole read
    request: it is framed as its last byte arrives (the bytes before go), the gap
    before it skipped on the way, with no timer needed."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x10", 1.0)
    stray = 1.0 + 3.5 * char
    f.receive_data(b"\xaa", stray)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(request, stray + (5 + len(request)) * char)
    events = [(str(ev.kind), ev.adu) for ev in f.events()]
    assert events == [("discard", b"\x01\x10\xaa"), ("request", request)]


def test_a_slave_address_above_127_is_no_exception_code(backend: ModuleType) -> None:
    """The exception bit is the function code's ([AP] 7), not the address's: at slave
    129 "81 0B" may be a Get Comm Event Counter request (4 bytes, [AP] 6.9), so 2
    more bytes, not the 6 of its 8-byte answer."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x81\x0b", 1.0)
    assert f.next_event() is None
    assert f.needed() == 4 - 2


def test_a_function_with_only_an_answer_rule_is_framed_by_its_length(
    backend: ModuleType,
) -> None:
    """A vendor function whose requests have no rule but whose answers are 6 bytes: a
    slave that hears one (another slave's answer) frames it by that length at once,
    a response, without waiting for the silence."""
    f = backend.Framer("slave", baudrate=9600, rules={0x41: (None, LengthRule.fixed(6))})
    adu = bytes(backend.add_crc(b"\x01\x41\xaa\xbb"))
    f.receive_data(adu, 1.0)
    assert [(str(ev.kind), ev.adu) for ev in f.events()] == [("response", adu)]


def test_positions_keep_counting_across_a_reset(backend: ModuleType) -> None:
    """reset() drops the buffered bytes (counted as truncated) but not their place in
    the stream: the request after 3 dropped bytes starts at offset 3."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x03\x00", 1.0)
    f.reset()
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(request, 1.5)
    assert [(str(ev.kind), ev.offset) for ev in f.events()] == [("request", 3)]
    assert f.counters["discarded_truncated"] == 3


def test_strict_gaps_around_a_stray_byte_agree_with_the_c_core(
    both: tuple[ModuleType, ModuleType],
) -> None:
    """Strict mode: a stray byte, a gap above t1.5, three bytes of a read request, a
    second such gap, its rest.  The request has a t1.5 gap inside ([SL] 2.5.1.1):
    not a frame; and the twin reports the discarded bytes as the C core does."""
    char = 11 / 9600
    seen = []
    for backend in both:
        f = backend.Framer("slave", baudrate=9600, strict=True)
        request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
        t = 1.0
        f.receive_data(b"\x07", t)
        t += (2.5 + 3) * char
        f.receive_data(request[:3], t)
        t += (2.5 + 5) * char
        f.receive_data(request[3:], t)
        f.handle_timer(t + 0.1)
        seen.append([(str(ev.kind), ev.error, ev.offset, ev.adu) for ev in f.events()])
    c_events, twin_events = seen
    assert all(kind == "discard" for kind, *_ in c_events)
    assert twin_events == c_events


def test_the_cores_reset_counts_only_the_bytes_left_unresolved(backend: ModuleType) -> None:
    """The core interface the client and the pymodbus framer drive directly (feed,
    poll, reset): a request and 3 more bytes fed, the request polled, then reset
    before the next poll: the 3 bytes not yet resolved are counted as truncated,
    not the request's 8 with them."""
    core = backend.Framer("slave", baudrate=9600).core
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    assert core.feed(request + b"\x01\x03\x00", 1_000_000) == 11
    event = core.poll()
    assert event is not None and event[6] == request
    core.reset()
    _frames, discarded, _runs = core.counts()
    assert list(discarded) == [0, 0, 0, 0, 0, 3]  # by reason: ..., truncated


def test_strict_a_gap_before_a_frame_is_not_inside_it(backend: ModuleType) -> None:
    """Strict mode: a stray byte, a gap above t1.5 (below t3.5), then a whole read
    request.  The gap ends the stray byte's bytes, not the request's ([SL] 2.5.1.1
    discards a frame with a gap between two of its characters): the byte goes, the
    request is framed."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600, strict=True)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(b"\x07", 1.0)
    end = 1.0 + (2.5 + len(request)) * char
    f.receive_data(request, end)
    f.handle_timer(end + 0.1)
    events = [(str(ev.kind), ev.adu) for ev in f.events()]
    assert events == [("discard", b"\x07"), ("request", request)]


def test_a_flush_silence_after_the_timer_still_drops_the_waiting_bytes(
    backend: ModuleType,
) -> None:
    """Lenient mode: "01 10" waits for its count byte; the timer notes the t3.5 silence
    after it (5 ms: the head waits on); the next bytes come 200 ms later, past the
    flush timeout (50 ms): that silence drops the two bytes at once (truncated),
    and the new bytes start afresh."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x10", 1.0)
    f.handle_timer(1.005)
    assert f.next_event() is None
    f.receive_data(b"\x01\x03", 1.2)
    assert [(str(ev.kind), ev.error, ev.adu) for ev in f.events()] == [
        ("discard", "truncated", b"\x01\x10")
    ]
    assert f.needed() == 5 - 2


def test_a_silence_behind_a_waiting_head_still_ends_the_frame_before_it(
    backend: ModuleType,
) -> None:
    """Lenient mode: a stray byte, then a whole request of a function whose length no
    rule gives (43 / MEI 13, [AP] 6.19), so the head waits (it could be an 8-byte
    Read Coils request); after a t3.5 silence one more byte; at the flush timeout
    the stray byte goes, the request is framed by the silence after it (which
    outlives the stray byte's discard), and the lone byte goes."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600)
    request = bytes(backend.add_crc(b"\x01\x2b\x0d\x00"))
    f.receive_data(b"\x01" + request, 1.0)
    f.receive_data(b"\xe2", 1.0 + 28 * char)
    assert f.next_event() is None
    f.handle_timer(1.25)
    events = [(str(ev.kind), ev.offset, ev.adu) for ev in f.events()]
    assert events == [("discard", 0, b"\x01"), ("request", 1, request), ("discard", 7, b"\xe2")]


def test_a_t35_of_one_microsecond_still_detects_silences(backend: ModuleType) -> None:
    """t3.5 set to 1 us (0 turns silence detection off, docs: pyrtu/core/line.py): a
    frame of a function without a length rule ends at the next silence."""
    f = backend.Framer("slave", baudrate=9600, t15=0, t35=1e-6)
    adu = bytes(backend.add_crc(b"\x01\x5a\xaa\xbb"))
    f.receive_data(adu, 1.0)
    assert f.next_event() is None
    f.receive_data(b"\x01\x03", 1.010)
    assert [(str(ev.kind), ev.adu) for ev in f.events()] == [("request", adu)]


def test_the_core_takes_no_byte_until_polled_after_a_closing_silence(
    backend: ModuleType,
) -> None:
    """csrc/rtu.h: rtu_framer_feed returns how many bytes it took; after a silence that
    ends what is buffered, none, again and again, until a poll resolved it."""
    core = backend.Framer("slave", baudrate=9600).core
    assert core.feed(b"\x01\x5a", 1_000_000) == 2
    assert core.feed(b"\x01\x03", 2_000_000) == 0  # a second of silence: poll first
    assert core.feed(b"\x01\x03", 2_000_000) == 0
    event = core.poll()
    assert event is not None and event[6] == b"\x01\x5a"  # dropped: truncated
    assert core.poll() is None
    assert core.feed(b"\x01\x03", 2_000_000) == 2


def test_a_long_read_of_noise_is_taken_as_the_c_core_takes_it(
    both: tuple[ModuleType, ModuleType],
) -> None:
    """2100 bytes of noise in one read: the twin's buffer holds twice the longest ADU
    (2048 bytes) as the C core's does (RTU_FRAMER_CAP), so both take 2048 at once,
    discard all but the last 256 (a frame up to max_adu, 256 bytes by [SL] 2.5.1, may
    still end in them) as one run, then take the rest: the same discard runs, at the
    same offsets."""
    junk = bytes((i * 97 + 13) % 256 for i in range(2100))
    seen = []
    for backend in both:
        f = backend.Framer("slave", baudrate=9600)
        f.receive_data(junk, 2.0)
        seen.append([(str(ev.kind), ev.offset, len(ev.adu)) for ev in f.events()])
    assert seen[0] == [
        ("discard", 0, 2048 - MAX_RTU_ADU),
        ("discard", 2048 - MAX_RTU_ADU, 2100 - 2048),
    ]
    assert seen[1] == seen[0]
    # the same after one byte went before: the buffer is all free again (compacted)
    seen = []
    for backend in both:
        f = backend.Framer("slave", baudrate=9600)
        f.receive_data(b"\x07", 1.0)
        f.handle_timer(1.1)
        f.receive_data(junk, 2.0)
        seen.append([(str(ev.kind), ev.offset, len(ev.adu)) for ev in f.events()])
    assert seen[0][1:] == [
        ("discard", 1, 2048 - MAX_RTU_ADU),
        ("discard", 1 + 2048 - MAX_RTU_ADU, 2100 - 2048),
    ]
    assert seen[1] == seen[0]


def test_a_master_needs_only_address_and_function_to_await_an_answer(
    backend: ModuleType,
) -> None:
    """The request context is its first two bytes (address and function): sent alone,
    they set it as a whole ADU does (the shortest answer: 5 bytes, [AP] 7)."""
    f = backend.Framer("master", baudrate=9600)
    f.send(b"\x01\x03")
    assert f.needed() == 5


def test_a_fifo_answers_byte_count_is_two_bytes_big_endian() -> None:
    """Read FIFO Queue ([AP] 6.18): address, 0x18, a 2-byte byte count (big-endian),
    then that many bytes, then the CRC: a count of 0x0102 is 258 bytes, 264 in all."""
    assert predict(RULES, DIR_RESPONSE, b"\x01\x18\x01\x02", 4) == (PRED_LENGTH, 6 + 258)


def test_single_writes_are_framed_by_their_length_at_once(backend: ModuleType) -> None:
    """Write Single Coil and Write Single Register ([AP] 6.5, 6.6): request and answer
    are 8 bytes, so each is framed as its last byte arrives, no silence needed."""
    for function in (5, 6):
        adu = bytes(backend.add_crc(bytes((1, function, 0, 1, 0xFF, 0))))
        slave = backend.Framer("slave", baudrate=9600)
        slave.receive_data(adu, 1.0)
        assert [(str(ev.kind), ev.adu) for ev in slave.events()] == [("request", adu)]
        master = backend.Framer("master", baudrate=9600)
        master.send(adu)
        master.receive_data(adu, 1.1)  # the echo of the request: the answer
        assert [(str(ev.kind), ev.adu) for ev in master.events()] == [("response", adu)]


def test_an_mei_request_needs_its_third_byte_to_decide(backend: ModuleType) -> None:
    """Function 43 ([AP] 6.19-6.21): its MEI type, the third byte, decides the length,
    so "01 2B" needs that byte and a CRC at least: 3 more (with a vendor's 64-byte
    answer to function 43, the request side alone bounds it)."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(b"\x01\x2b", 1.0)
    assert f.needed() == 3
    f = backend.Framer("slave", baudrate=9600, rules={43: (None, LengthRule.fixed(64))})
    f.receive_data(b"\x01\x2b", 1.0)
    assert f.needed() == 3


def test_file_record_frames_are_framed_by_their_byte_count(backend: ModuleType) -> None:
    """Read and Write File Record ([AP] 6.14, 6.15): after address and function a byte
    count gives the rest, both ways (the write's answer echoes its request), so each
    is framed as its last byte arrives.  Write: one sub-request (reference type 6,
    file 4, record 1, one register 0x1234): 9 bytes counted, 14 in all; read: the
    same record (7 bytes counted), its answer 4 (length 3, type 6, 0x1234)."""
    write = bytes(backend.add_crc(bytes.fromhex("0115 09 06 0004 0001 0001 1234")))
    read = bytes(backend.add_crc(bytes.fromhex("0114 07 06 0004 0001 0001")))
    answer = bytes(backend.add_crc(bytes.fromhex("0114 04 03 06 1234")))
    for request, response in ((write, write), (read, answer)):
        slave = backend.Framer("slave", baudrate=9600)
        slave.receive_data(request, 1.0)
        assert [(str(ev.kind), ev.adu) for ev in slave.events()] == [("request", request)]
        master = backend.Framer("master", baudrate=9600)
        master.send(request)
        master.receive_data(response, 1.1)
        assert [(str(ev.kind), ev.adu) for ev in master.events()] == [("response", response)]


#: every public function code of [AP] 6 with its length rule: a request and an answer
#: laid out as the spec draws them (address 1; CRC added by the backend)
SPEC_FRAMES = {
    1: ("0101 0013 0013", "0101 03 cd6b05"),  # 6.1: 19 coils from 20; 3 bytes of status
    2: ("0102 00c4 0016", "0102 03 acdb35"),  # 6.2
    3: ("0103 006b 0003", "0103 06 022b00000064"),  # 6.3
    4: ("0104 0008 0001", "0104 02 000a"),  # 6.4
    7: ("0107", "0107 6d"),  # 6.7: Read Exception Status
    8: ("0108 0000 a537", "0108 0000 a537"),  # 6.8: Return Query Data, echoed
    11: ("010b", "010b ffff 0108"),  # 6.9: Get Comm Event Counter
    12: ("010c", "010c 08 0000 0108 0121 2000"),  # 6.10: Get Comm Event Log
    15: ("010f 0013 000a 02 cd01", "010f 0013 000a"),  # 6.11
    16: ("0110 0001 0002 04 000a 0102", "0110 0001 0002"),  # 6.12
    17: ("0111", "0111 03 01 ff 00"),  # 6.13: Report Server ID
    22: ("0116 0004 00f2 0025", "0116 0004 00f2 0025"),  # 6.16: Mask Write, echoed
    23: ("0117 0003 0006 000e 0003 06 00ff 00ff 00ff", "0117 0c" + "00fe" * 6),  # 6.17
    24: ("0118 04de", "0118 0006 0002 01b8 1284"),  # 6.18: Read FIFO Queue
}


def test_every_public_function_is_framed_by_its_length(backend: ModuleType) -> None:
    """Each public function's request (to a slave) and answer (to the master that sent
    it) is framed as its last byte arrives: by the length its rule gives, no silence
    needed; the frames as [AP] 6 draws them."""
    for function, (request_hex, answer_hex) in SPEC_FRAMES.items():
        request = bytes(backend.add_crc(bytes.fromhex(request_hex)))
        answer = bytes(backend.add_crc(bytes.fromhex(answer_hex)))
        slave = backend.Framer("slave", baudrate=9600)
        slave.receive_data(request, 1.0)
        got = [(str(ev.kind), ev.adu) for ev in slave.events()]
        assert got == [("request", request)], function
        master = backend.Framer("master", baudrate=9600)
        master.send(request)
        master.receive_data(answer, 1.1)
        got = [(str(ev.kind), ev.adu) for ev in master.events()]
        assert got == [("response", answer)], function


def test_a_vendor_count_rule_bounds_the_wait_with_its_own_tail(backend: ModuleType) -> None:
    """A vendor request whose count byte sits at offset 4 with 6 bytes after the
    counted part: before the count is in, the shortest frame is 4 + 1 + 0 + 6 = 11
    bytes, so "01 41" needs 9 more (its tail, not a CRC's 2)."""
    f = backend.Framer("slave", baudrate=9600, rules={0x41: (LengthRule.counted(4, 1, 1, 6), None)})
    f.receive_data(b"\x01\x41", 1.0)
    assert f.needed() == 11 - 2


def test_a_monitor_takes_the_echo_of_an_odd_function_as_the_answer(backend: ModuleType) -> None:
    """A monitor hears Write Single Coil (function 5, [AP] 6.5) and then the same 8
    bytes again: the slave's echo, its answer (a request and its answer are the same
    length here, so only the request just seen tells them apart)."""
    f = backend.Framer("monitor", baudrate=9600)
    request = bytes(backend.add_crc(b"\x01\x05\x00\x01\xff\x00"))
    f.receive_data(request, 1.0)
    f.receive_data(request, 1.1)
    assert [str(ev.kind) for ev in f.events()] == ["request", "response"]


def test_a_t15_of_one_microsecond_still_detects_gaps(backend: ModuleType) -> None:
    """Strict mode with t1.5 set to 1 us (0 turns it off): a gap of 0.5 ms inside a
    read request makes it incomplete ([SL] 2.5.1.1): discarded, reason t1.5."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600, strict=True, t15=1e-6, t35=0.004)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(request[:4], 1.0)
    f.receive_data(request[4:], 1.0 + 0.0005 + 4 * char)
    f.handle_timer(1.1)
    assert [(str(ev.kind), ev.error) for ev in f.events()] == [("discard", "t1.5")]


def test_three_bytes_whose_crc_checks_are_no_frame(backend: ModuleType) -> None:
    """An RTU frame is at least address, function and CRC: 4 bytes ([SL] 2.5.1.2).
    An address and its own CRC (3 bytes) that end at a silence are discarded."""
    f = backend.Framer("slave", baudrate=9600)
    three = bytes(backend.add_crc(b"\x01"))
    f.receive_data(three, 1.0)
    f.handle_timer(1.1)
    assert [str(ev.kind) for ev in f.events()] == ["discard"]


def test_a_read_request_exactly_max_adu_long_is_framed(backend: ModuleType) -> None:
    """A length equal to max_adu is within it: with max_adu 8 the read request of
    [AP] 6.3 ("11 03 00 6B 00 03", CRC 76 87 as the spec prints it) is framed as its
    last byte arrives, not refused as too long."""
    request = bytes.fromhex("11 03 00 6B 00 03 76 87")
    f = backend.Framer("slave", baudrate=9600, max_adu=8)
    f.receive_data(request, 1.0)
    assert [(str(ev.kind), ev.error, ev.adu) for ev in f.events()] == [("request", None, request)]


def test_a_deadline_one_microsecond_below_the_int64_range_is_a_timer(
    backend: ModuleType,
) -> None:
    """The core's times are int64 microseconds (csrc/rtu_internal.h); INT64_MAX, 2**63 - 1,
    means no timer.  Bytes whose t3.5 ends at 2**63 - 2 have that deadline; one
    microsecond later it would be INT64_MAX itself: none.  t3.5 at 9600 baud, 11 bits a
    character ([SL] 2.5.1.1): 3.5 x 11 / 9600 s, 4010 us to the microsecond."""
    t35_us = round(3.5 * 11 * 1_000_000 / 9600)
    assert t35_us == 4010
    core = backend.Framer("slave", baudrate=9600).core
    assert core.feed(b"\x01\x03", 2**63 - 2 - t35_us) == 2
    assert core.deadline() == 2**63 - 2
    core = backend.Framer("slave", baudrate=9600).core
    assert core.feed(b"\x01\x03", 2**63 - 1 - t35_us) == 2
    assert core.deadline() is None


def test_a_silence_at_the_end_of_a_full_window_agrees_with_the_c_core(
    both: tuple[ModuleType, ModuleType],
) -> None:
    """The core driven directly, polled only at the end: with max_adu 4, "01 10" and its
    CRC, a timer past t3.5, two more bytes: the silence mark sits exactly at the end
    of the 4-byte window, the bytes after it make the window closed.  The twin
    resolves these bytes as the C core does."""
    seen = []
    for backend in both:
        core = backend.Framer("slave", baudrate=9600, max_adu=4).core
        four = bytes(backend.add_crc(b"\x01\x10"))
        assert core.feed(four, 1_000_000) == 4
        core.handle_timer(1_010_000)  # 10 ms: past t3.5 (4 ms), short of the flush (50)
        assert core.feed(b"\x01\x03", 1_012_000) == 2
        events = []
        while (event := core.poll()) is not None:
            events.append(event)
        seen.append(events)
    c_events, twin_events = seen
    assert c_events and twin_events == c_events


def test_a_request_past_max_adu_still_lets_the_answer_be_framed(backend: ModuleType) -> None:
    """A slave hears another slave's Write Multiple Registers answer ([AP] 6.12:
    "11 10 00 01 00 02", 8 bytes with its CRC).  Read as a request its "count" (the
    CRC's low byte) runs past max_adu 8: ruled out, the answer is tried next and
    framed as its last byte arrives, with no silence."""
    answer = bytes(backend.add_crc(bytes.fromhex("11 10 00 01 00 02")))
    f = backend.Framer("slave", baudrate=9600, max_adu=8)
    f.receive_data(answer, 1.0)
    assert [(str(ev.kind), ev.adu) for ev in f.events()] == [("response", answer)]


def test_a_shortest_frame_exactly_max_adu_long_bounds_the_wait(backend: ModuleType) -> None:
    """Write Single Register ([AP] 6.6): request and answer are 8 bytes.  With max_adu 8
    a slave that has "11 06" still needs 6 bytes: a length equal to max_adu bounds
    the wait as any shorter one does."""
    f = backend.Framer("slave", baudrate=9600, max_adu=8)
    f.receive_data(b"\x11\x06", 1.0)
    assert f.next_event() is None
    assert f.needed() == 8 - 2


def test_silence_marks_past_a_discarded_byte_are_kept(backend: ModuleType) -> None:
    """Lenient mode: a read request to slave 17 ([AP] 6.3), a stray byte, a t3.5 silence,
    six bytes "01 03 00 01" and their CRC (short of a read request's 8: they wait),
    another t3.5 silence, a read request to slave 1.  Pieces delimited by silences
    ([SL] 2.5.1.1), resolved as the last byte arrives: the stray byte goes; the six
    bytes are a frame by their CRC, ended by the second silence (which must outlive
    the stray byte's discard; a slave calls what a silence frames a request); then
    the request."""
    char = 11 / 9600
    first = bytes.fromhex("11 03 00 6B 00 03 76 87")
    six = bytes(backend.add_crc(b"\x01\x03\x00\x01"))
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f = backend.Framer("slave", baudrate=9600)
    t = 1.0
    f.receive_data(first, t)
    t += 5 * char  # 5 characters of silence: past t3.5, short of the flush
    f.receive_data(b"\x07", t)
    t += (5 + len(six)) * char
    f.receive_data(six, t)
    t += (5 + len(request)) * char
    f.receive_data(request, t)
    events = [(str(ev.kind), ev.offset, ev.adu) for ev in f.events()]
    assert events == [
        ("request", 0, first),
        ("discard", 8, b"\x07"),
        ("request", 9, six),
        ("request", 15, request),
    ]


def test_the_core_takes_bytes_again_once_a_closing_silence_is_resolved(
    backend: ModuleType,
) -> None:
    """csrc/rtu.h: after a silence that closes the buffered bytes the core takes no byte
    until they are resolved; once a poll has resolved them all (here the read request
    of [AP] 6.3, "11 03 00 6B 00 03 76 87", one event), the next bytes are taken at
    once, before any further poll."""
    request = bytes.fromhex("11 03 00 6B 00 03 76 87")
    core = backend.Framer("slave", baudrate=9600).core
    assert core.feed(request, 1_000_000) == 8
    core.handle_timer(2_000_000)  # a second of silence: past the flush timeout, closed
    assert core.feed(request, 2_000_000) == 0
    event = core.poll()
    assert event is not None and event[6] == request
    assert core.feed(request, 3_000_000) == 8


def _events(core: Any) -> list[tuple[int, int, bytes]]:
    """(kind, error, bytes) of every event the core has ready (Framer.core's poll)."""
    out = []
    while (event := core.poll()) is not None:
        out.append((event[2], event[3], event[6]))
    return out


def test_a_timer_at_the_flush_deadline_closes_the_waiting_bytes(backend: ModuleType) -> None:
    """Lenient mode, flush timeout 20 ms: "01 10" waits for its count byte; the timer
    at t3.5 notes the silence and sets the next deadline, the flush: a silence of
    exactly the flush timeout drops the bytes (truncated), one microsecond less
    does not."""
    for now, dropped in ((1_020_000, True), (1_019_999, False)):
        core = backend.Framer("slave", baudrate=9600, flush_timeout=0.02).core
        assert core.feed(b"\x01\x10", 1_000_000) == 2
        assert _events(core) == []
        core.handle_timer(1_005_000)  # past t3.5 (4010 us)
        assert _events(core) == []
        assert core.deadline() == 1_020_000
        core.handle_timer(now)
        assert [adu for _kind, _error, adu in _events(core)] == ([b"\x01\x10"] if dropped else [])


def test_bytes_after_exactly_the_flush_timeout_start_afresh(backend: ModuleType) -> None:
    """Lenient mode, flush timeout 20 ms: "01 10" waits for its count byte; one more
    byte whose silence before it (its arrival less one character, 11 bits at 9600
    baud: 1146 us, less the last arrival) is exactly the flush timeout: the waiting
    bytes go first (truncated), then the byte is taken; one microsecond less and
    it joins them."""
    char_us = round(11 * 1_000_000 / 9600)
    for silence, dropped in ((20_000, True), (19_999, False)):
        core = backend.Framer("slave", baudrate=9600, flush_timeout=0.02).core
        assert core.feed(b"\x01\x10", 1_000_000) == 2
        assert _events(core) == []
        now = 1_000_000 + char_us + silence
        took = core.feed(b"\x07", now)
        events = _events(core)
        if took == 0:
            took = core.feed(b"\x07", now)
        assert took == 1
        assert [adu for _kind, _error, adu in events] == ([b"\x01\x10"] if dropped else [])


def test_reset_forgets_the_awaited_answer(backend: ModuleType) -> None:
    """reset() drops the request context too (pyrtu.Framer.reset): a master that sent a
    read request awaits an answer of 5 bytes at least ([AP] 7: an exception
    answer); after reset() it awaits nothing."""
    f = backend.Framer("master", baudrate=9600)
    f.send(bytes.fromhex("11 03 00 6B 00 03 76 87"))
    assert f.needed() == 5
    f.reset()
    assert f.needed() == 0


def test_a_t15_of_zero_detects_no_gap(backend: ModuleType) -> None:
    """Strict mode with t1.5 set to 0, which turns gap detection off (pyrtu/core/line.py):
    a read request with 0.5 ms of silence inside is framed, not discarded."""
    char = 11 / 9600
    f = backend.Framer("slave", baudrate=9600, strict=True, t15=0, t35=0.004)
    request = bytes(backend.add_crc(b"\x01\x03\x00\x00\x00\x01"))
    f.receive_data(request[:4], 1.0)
    f.receive_data(request[4:], 1.0 + 0.0005 + 4 * char)
    assert [(str(ev.kind), ev.adu) for ev in f.events()] == [("request", request)]


def _stuck(signum: int, frame: object) -> None:
    raise TimeoutError("the framer did not return (a loop that never ends)")


def test_a_silence_mark_behind_the_head_begins_no_later_frame(backend: ModuleType) -> None:
    """Lenient mode: a stray byte, a t3.5 silence, then in one read four bytes 5A (no
    length rule), "5A 10" (slave 90's Write Multiple Registers request, [AP] 6.12: 9
    bytes at least) and "01 5A" with its CRC.  At the t3.5 timer the bytes before
    "5A 10" go one by one (their lengths fail), and "5A 10 ..." waits for its count
    byte: the silence mark it has left behind begins no frame inside it, not even one
    that would end exactly at its end.  At the flush, "5A 10" goes, and "01 5A ..."
    is a frame by its CRC.  (A guard stops a framer that would loop for ever.)"""
    char = 11 / 9600
    tail = bytes(backend.add_crc(b"\x01\x5a"))
    rest = b"\x5a" * 4 + b"\x5a\x10" + tail
    end = 1.0 + (5 + len(rest)) * char  # 5 characters of silence after the stray byte
    f = backend.Framer("slave", baudrate=9600)
    old = signal.signal(signal.SIGALRM, _stuck)
    signal.setitimer(signal.ITIMER_REAL, 5.0)
    try:
        f.receive_data(b"\x07", 1.0)
        f.receive_data(rest, end)
        assert f.next_event() is None
        f.handle_timer(end + 0.005)  # past t3.5 (4 ms), short of the flush (50)
        at_t35 = [(str(ev.kind), ev.offset, ev.adu) for ev in f.events()]
        f.handle_timer(end + 1.0)
        at_flush = [(str(ev.kind), ev.offset, ev.adu) for ev in f.events()]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert at_t35 == [("discard", 0, b"\x07" + b"\x5a" * 4)]
    assert at_flush == [("discard", 5, b"\x5a\x10"), ("request", 7, tail)]


def test_a_t35_of_zero_ends_no_frame_by_a_silence(backend: ModuleType) -> None:
    """t3.5 set to 0 turns silence detection off (pyrtu/core/line.py): a frame of a
    function without a length rule is not ended by the 10 ms of silence before the
    next bytes (with t3.5 of 1 us it is: test_a_t35_of_one_microsecond_...)."""
    f = backend.Framer("slave", baudrate=9600, t15=0, t35=0)
    adu = bytes(backend.add_crc(b"\x01\x5a\xaa\xbb"))
    f.receive_data(adu, 1.0)
    f.receive_data(b"\x01\x03", 1.010)
    assert f.next_event() is None


def _with_crc(body: bytes) -> bytes:
    crc = crc_bitwise(body)  # [SL] 6.2.2 bit by bit: nothing from pyrtu
    return body + bytes((crc & 0xFF, crc >> 8))


@pytest.mark.parametrize("max_adu", [8, MAX_RTU_ADU])
def test_a_frame_exactly_max_adu_long_that_only_its_silence_ends_is_framed(
    backend: ModuleType, max_adu: int
) -> None:
    """Function 0x5A has no length rule: only the t3.5 silence after it ends the frame
    ([SL] 2.5.1.1).  A frame exactly max_adu long (at the default, 256 bytes: the
    longest RTU frame [SL] 2.5.1 allows) waits for that silence as a shorter one does,
    and is framed whole; it was discarded byte by byte (the window full, the core
    stopped waiting one byte early)."""
    frame = _with_crc(b"\x01\x5a" + bytes(max_adu - 4))
    assert len(frame) == max_adu
    f = backend.Framer("slave", baudrate=9600, max_adu=max_adu)
    f.receive_data(frame, 1.0)
    assert f.next_event() is None  # no silence yet: it waits
    f.handle_timer(1.1)  # 100 ms: past t3.5 and the flush
    assert [(str(ev.kind), ev.adu) for ev in f.events()] == [("request", frame)]
    # the same bytes in one capture, ended by the capture's end
    frames = backend.parse_stream(frame, role="slave", baudrate=9600, max_adu=max_adu)
    assert [bytes(fr.adu) for fr in frames] == [frame]


def test_a_frame_one_byte_past_max_adu_is_still_discarded(backend: ModuleType) -> None:
    """The boundary's other side: 9 bytes with max_adu 8 never make a frame."""
    frame = _with_crc(b"\x01\x5a" + bytes(5))
    assert len(frame) == 9
    f = backend.Framer("slave", baudrate=9600, max_adu=8)
    f.receive_data(frame, 1.0)
    f.handle_timer(1.1)
    events = f.events()
    assert events and all(str(ev.kind) == "discard" for ev in events)
    assert b"".join(bytes(ev.adu) for ev in events) == frame
