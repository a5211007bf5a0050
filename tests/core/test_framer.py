"""The sans-I/O framer: timing, roles, resynchronisation, counters (both backends)."""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu import BONFIGLIOLI, ErrorReason, FrameKind, LengthRule

REQ = bytes.fromhex("010300000002")  # read 2 holding registers of slave 1
RESP = bytes.fromhex("01030400010002")


def feed_bytes(f: object, adu: bytes, t0: float, spacing: float) -> float:
    """One byte at a time, `spacing` seconds apart (arrival to arrival); returns the last time."""
    t = t0
    for i, b in enumerate(adu):
        t = t0 + i * spacing
        f.receive_data(bytes((b,)), t)  # type: ignore[attr-defined]
    return t


# --- timing at 9600 baud (8E1: 11 bits, char 1146 us, t1.5 1719 us, t3.5 4010 us) ---


def test_char_timing_values(backend: ModuleType) -> None:
    t = backend.char_timing(9600)
    assert (t.char_us, t.t15_us, t.t35_us) == (1146, 1719, 4010)  # CFW100 table 4.1
    t = backend.char_timing(9600, parity="N")  # 8N1: 10 bits
    assert (t.char_us, t.t15_us, t.t35_us) == (1042, 1563, 3646)
    assert backend.char_timing(9600, parity="N", stopbits=2).char_us == 1146  # 8N2: 11 bits
    t = backend.char_timing(19200)
    assert (t.char_us, t.t15_us, t.t35_us) == (573, 859, 2005)
    t = backend.char_timing(115200)
    assert (t.t15_us, t.t35_us) == (750, 1750)  # Serial Line V1.02 2.5.1.1
    t = backend.char_timing(115200, timing="weg")
    assert (t.t15_us, t.t35_us) == (860, 2005)  # WEG table 4.1: 573 us, 2.005 ms
    t = backend.char_timing(9600, t15=0.003, t35=0.010)
    assert (t.t15_us, t.t35_us) == (3000, 10000)


@pytest.mark.parametrize("extra_chars", [0.0, 1.0])
def test_bytes_spaced_by_one_char_stay_one_frame(backend: ModuleType, extra_chars: float) -> None:
    f = backend.Framer("slave", baudrate=9600, strict=True)
    char = 1146e-6
    adu = backend.add_crc(REQ)
    feed_bytes(f, adu, 1.0, char * (1 + extra_chars))
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu


def test_gap_over_t15_discards_in_strict_mode(backend: ModuleType) -> None:
    adu = backend.add_crc(REQ)
    char = 1146e-6
    f = backend.Framer("slave", baudrate=9600, strict=True)
    t = feed_bytes(f, adu[:4], 1.0, char)
    t += char + 2.0 * char  # a silence of 2 chars (> t1.5, < t3.5)
    feed_bytes(f, adu[4:], t, char)
    f.handle_timer(10.0)
    events = f.events()
    assert all(e.error is not None for e in events)
    assert events[0].error == ErrorReason.T15
    assert sum(len(e.adu) for e in events) == len(adu)
    assert f.counters["discarded_t1.5"] >= 1
    # Lenient mode takes the same bytes as a frame: the gap is only a hint.
    g = backend.Framer("slave", baudrate=9600)
    t = feed_bytes(g, adu[:4], 1.0, char)
    feed_bytes(g, adu[4:], t + 3.0 * char, char)
    ev = g.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu


def test_t35_silence_ends_a_frame_of_unknown_length(backend: ModuleType) -> None:
    """A vendor code with no rule ends at t3.5 of silence, not before."""
    adu = backend.add_crc(bytes.fromhex("07550102030405"))
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(adu, 2.0)
    assert f.next_event() is None
    deadline = f.timer()
    assert deadline == pytest.approx(2.0 + 0.004010)
    f.handle_timer(deadline - 2e-6)
    assert f.next_event() is None
    f.handle_timer(deadline)
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu and ev.kind == FrameKind.REQUEST
    assert f.timer() is None


def test_t35_gap_splits_in_strict_mode(backend: ModuleType) -> None:
    adu = backend.add_crc(REQ)
    f = backend.Framer("slave", baudrate=9600, strict=True)
    f.receive_data(adu[:3], 1.0)
    f.receive_data(adu[3:], 1.0 + 0.0045 + 5 * 1146e-6)  # >= t3.5 of silence between
    f.handle_timer(2.0)
    events = f.events()
    # the head is cut short; the tail starts with function code 0
    assert [e.error for e in events] == [ErrorReason.TRUNCATED, ErrorReason.UNKNOWN_FUNCTION]
    assert [len(e.adu) for e in events] == [3, 5]


def test_fixed_timing_at_115200(backend: ModuleType) -> None:
    adu = backend.add_crc(bytes.fromhex("07550102"))
    for rule, t35 in (("modbus", 1750e-6), ("weg", 2005e-6)):
        f = backend.Framer("slave", baudrate=115200, timing=rule)
        f.receive_data(adu, 5.0)
        assert f.timer() == pytest.approx(5.0 + t35)
        f.handle_timer(5.0 + t35)
        ev = f.next_event()
        assert ev is not None and ev.adu == adu


def test_strict_t15_at_115200_uses_750us(backend: ModuleType) -> None:
    adu = backend.add_crc(REQ)
    char = 11 / 115200
    for gap, ok in ((700e-6, True), (800e-6, False)):
        f = backend.Framer("slave", baudrate=115200, strict=True)
        f.receive_data(adu[:5], 1.0)
        f.receive_data(adu[5:], 1.0 + gap + 3 * char)
        f.handle_timer(2.0)
        ev = f.next_event()
        assert ev is not None and (ev.error is None) is ok


def test_usb_batched_frame_across_a_gap(backend: ModuleType) -> None:
    """An FTDI adapter delivers half a frame, then the rest 16 ms later."""
    adu = backend.add_crc(bytes.fromhex("0110000000020400010002"))
    f = backend.Framer("slave", baudrate=19200)
    f.receive_data(adu[:6], 1.0)
    f.handle_timer(1.0 + 0.003)  # t3.5 passes: lenient mode keeps the bytes
    assert f.next_event() is None
    f.receive_data(adu[6:], 1.016)
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu
    s = backend.Framer("slave", baudrate=19200, strict=True)
    s.receive_data(adu[:6], 1.0)
    s.receive_data(adu[6:], 1.016)
    s.handle_timer(2.0)
    assert all(e.error for e in s.events())


#: an FC 03 answer of 4 registers (13 bytes) whose first 12 bytes also end in a CRC
#: that checks: CRC16(03 03 08 03ff 0400 0401 04) = 0x0302.  Seen on the virtual bus
#: under load (tests/drivers/test_aio_master.py, slave 3 at register 23): the 13th byte came
#: after a t3.5 gap and the master took the 12 bytes as an answer, "response PDU has 9
#: bytes, expected 10".
PREFIX_CHECKS = bytes.fromhex("03 03 08 03ff 0400 0401 0402 0300")


def test_a_prefix_whose_crc_checks_does_not_cut_a_predicted_frame(backend: ModuleType) -> None:
    """Lenient mode keeps bytes across a gap while the header promises more: the
    12-byte prefix is no frame, the whole answer is; strict mode closes the frame at
    the gap (the prefix is then a frame of its own, as [SL] 2.5.1.1 says)."""
    answer = PREFIX_CHECKS
    assert backend.add_crc(answer[:10]) == answer[:12]  # the coincidence itself
    assert backend.add_crc(answer[:11]) == answer
    char = 286e-6  # 38400 baud 8N1; t3.5 = 1.75 ms above 19200
    for role in ("master", "monitor", "slave"):
        f = backend.Framer(role, baudrate=38400, parity="N")
        f.receive_data(answer[:12], 1.0)
        f.handle_timer(1.0 + 0.003)  # t3.5 passes, the flush does not
        assert f.next_event() is None, role
        f.receive_data(answer[12:], 1.006 + char)
        ev = f.next_event()
        assert ev is not None and ev.error is None and ev.adu == answer, role
    s = backend.Framer("master", baudrate=38400, parity="N", strict=True)
    s.receive_data(answer[:12], 1.0)
    s.handle_timer(1.003)
    ev = s.next_event()
    assert ev is not None and ev.error is None and ev.adu == answer[:12]
    # lenient, and the silence closes the frame (the flush): the prefix is a frame then
    f = backend.Framer("master", baudrate=38400, parity="N", flush_timeout=0.02)
    f.receive_data(answer[:12], 1.0)
    f.handle_timer(1.003)
    assert f.next_event() is None
    f.handle_timer(1.02)
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == answer[:12]


def test_valid_frame_after_gap_beats_incomplete_bytes(backend: ModuleType) -> None:
    f = backend.Framer("slave", baudrate=19200)
    junk = bytes.fromhex("0110000000020400")  # FC 16 head that promises 13 bytes
    adu = backend.add_crc(REQ)
    f.receive_data(junk, 1.0)
    f.receive_data(adu, 1.010)
    events = f.events()
    assert [(e.kind, e.error) for e in events] == [
        (FrameKind.DISCARD, ErrorReason.TRUNCATED),
        (FrameKind.REQUEST, None),
    ]
    assert events[1].adu == adu


def test_lenient_flush_timeout_drops_incomplete_bytes(backend: ModuleType) -> None:
    f = backend.Framer("slave", baudrate=19200, flush_timeout=0.02)
    f.receive_data(bytes.fromhex("01100000"), 1.0)
    f.handle_timer(1.003)
    assert f.next_event() is None
    assert f.timer() == pytest.approx(1.02)
    f.handle_timer(1.02)
    ev = f.next_event()
    assert ev is not None and ev.error == ErrorReason.TRUNCATED and len(ev.adu) == 4
    assert f.counters["discarded_truncated"] == 4


# --- roles and classification ---------------------------------------------------


def test_slave_sizes_other_slaves_responses(backend: ModuleType) -> None:
    """A response whose data holds a valid request for us is not taken as a request."""
    inner = backend.add_crc(bytes.fromhex("2a0600010003"))  # write request to slave 42
    request = backend.add_crc(bytes.fromhex("0503000000") + bytes((5,)))  # slave 5, 5 regs
    payload = inner + b"\x00\x00"
    response = backend.add_crc(bytes.fromhex("05030a") + payload)
    f = backend.Framer("slave", baudrate=19200)
    f.receive_data(request + response, 1.0)  # one USB burst, no gap at all
    events = f.events()
    assert [(e.kind, e.address) for e in events] == [
        (FrameKind.REQUEST, 5),
        (FrameKind.RESPONSE, 5),
    ]
    assert events[1].adu == response


def test_monitor_classifies_by_context(backend: ModuleType) -> None:
    req = backend.add_crc(bytes.fromhex("0106000a0102"))
    echo = req  # FC 06 response echoes the request
    exc = backend.add_crc(bytes.fromhex("018602"))
    bcast = backend.add_crc(bytes.fromhex("0006000a0102"))
    frames = backend.parse_stream(req + echo + req + exc + bcast + bcast, "monitor")
    assert [f.kind for f in frames] == [
        FrameKind.REQUEST,
        FrameKind.RESPONSE,
        FrameKind.REQUEST,
        FrameKind.EXCEPTION,
        FrameKind.REQUEST,  # broadcast: no response follows
        FrameKind.REQUEST,
    ]
    assert frames[3].exception_code == 2


def test_master_role_ignores_request_rules(backend: ModuleType) -> None:
    f = backend.Framer("master", baudrate=19200)
    f.send(backend.add_crc(REQ))
    resp = backend.add_crc(RESP)
    f.receive_data(resp, 1.0)
    ev = f.next_event()
    assert ev is not None and ev.kind == FrameKind.RESPONSE and ev.adu == resp


@pytest.mark.parametrize(
    "hexpdu",
    [
        "0107",  # FC 07 request
        "018100",  # not a frame: exception of FC 1 with code 0 ... still 5 bytes
        "010B",
        "0111",
        "010C",
        "01160001ff000000",
        "0117000000020000000102000a",
        "01180004",
        "01140706000400010002",
        "012B0E0100",
    ],
)
def test_request_lengths_predicted(backend: ModuleType, hexpdu: str) -> None:
    adu = backend.add_crc(bytes.fromhex(hexpdu))
    role = "master" if bytes.fromhex(hexpdu)[1] & 0x80 else "slave"
    f = backend.Framer(role, baudrate=9600)
    f.receive_data(adu, 1.0)
    ev = f.next_event()
    assert ev is not None and ev.adu == adu


@pytest.mark.parametrize(
    "hexpdu",
    [
        "010700",
        "010B00000003",
        "010C080000000100020003",
        "0111030aff00",
        "01180008000300010002000f",  # FIFO: 2-byte byte count
        "01170400010002",
        "01140c050600010002050600030004",
        "01080000a537",
        # 43/14 with three objects: walk of the objects
        "012B0E01010000030003414243010244450203563132",
    ],
)
def test_response_lengths_predicted(backend: ModuleType, hexpdu: str) -> None:
    adu = backend.add_crc(bytes.fromhex(hexpdu))
    f = backend.Framer("master", baudrate=9600)
    for i in range(len(adu)):  # byte by byte: the walk needs steps
        f.receive_data(adu[i : i + 1], 1.0 + i * 1e-3)
    ev = f.next_event()
    assert ev is not None and ev.error is None and ev.adu == adu


def test_vendor_rules_end_frames_without_silence(backend: ModuleType) -> None:
    req = backend.add_crc(bytes.fromhex("016401e1"))  # Bonfiglioli FC 100
    plain = backend.Framer("slave", baudrate=9600)
    plain.receive_data(req, 1.0)
    assert plain.next_event() is None  # needs the silence
    f = backend.Framer("slave", baudrate=9600, rules=BONFIGLIOLI)
    f.receive_data(req, 1.0)
    ev = f.next_event()
    assert ev is not None and ev.adu == req
    rules = {0x44: (LengthRule.counted(2, width=1, scale=2), LengthRule.fixed(5))}
    g = backend.Framer("slave", baudrate=9600, rules=rules)
    counted = backend.add_crc(bytes.fromhex("014402") + bytes(4))
    g.receive_data(counted, 1.0)
    ev = g.next_event()
    assert ev is not None and ev.adu == counted


def test_overflow_and_max_adu(backend: ModuleType) -> None:
    big = backend.add_crc(bytes.fromhex("01100000003264") + bytes(100))  # 109 bytes
    f = backend.Framer("slave", baudrate=19200, max_adu=64)  # the WEG telegram limit
    f.receive_data(big, 1.0)
    f.handle_timer(2.0)
    events = f.events()
    assert events[0].error == ErrorReason.OVERFLOW
    assert all(e.error for e in events)
    ok = backend.Framer("slave", baudrate=19200)
    ok.receive_data(big, 1.0)
    assert ok.next_event().adu == big  # type: ignore[union-attr]


def test_unknown_function_reason_without_timing(backend: ModuleType) -> None:
    frames = backend.parse_stream(bytes.fromhex("0155") + backend.add_crc(REQ), "slave")
    assert frames[0].error == ErrorReason.UNKNOWN_FUNCTION
    assert frames[1].adu == backend.add_crc(REQ)


def test_reset_drops_bytes_and_context(backend: ModuleType) -> None:
    f = backend.Framer("slave", baudrate=19200)
    f.receive_data(b"\x01\x03\x00", 1.0)
    f.reset()
    assert f.counters["discarded_truncated"] == 3
    f.receive_data(backend.add_crc(REQ), 2.0)
    assert f.next_event().adu == backend.add_crc(REQ)  # type: ignore[union-attr]


def test_send_returns_bytes_and_frame_times(backend: ModuleType) -> None:
    f = backend.Framer("master", baudrate=9600)
    assert f.send(bytearray(backend.add_crc(REQ))) == backend.add_crc(REQ)
    resp = backend.add_crc(RESP)
    f.receive_data(resp, 3.0)
    ev = f.next_event()
    assert ev is not None
    assert ev.end == pytest.approx(3.0)
    assert ev.start == pytest.approx(3.0 - len(resp) * 1146e-6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"role": "sniffer"}, "role"),
        ({"baudrate": 0}, "baudrate"),
        ({"parity": "X"}, "parity"),
        ({"stopbits": 3}, "stopbits"),
        ({"bytesize": 9}, "bytesize"),
        ({"timing": "fast"}, "timing"),
        ({"t35": -1}, "t35"),
        ({"t15": float("nan")}, "t15"),
        ({"max_adu": 2000}, "max_adu"),
        ({"rules": {200: (None, None)}}, "function code"),
        ({"rules": {100: (6, 8)}}, "LengthRule"),
    ],
)
def test_bad_arguments_raise_value_error(
    backend: ModuleType, kwargs: dict[str, object], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        backend.Framer(**kwargs)


def test_bad_data_types(backend: ModuleType) -> None:
    f = backend.Framer("slave")
    with pytest.raises(TypeError, match="bytes-like"):
        f.receive_data("0103", 1.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="bytes-like"):
        backend.crc16("123")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="crc"):
        backend.crc16(b"1", crc=0x10000)
