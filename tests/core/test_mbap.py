"""MBAP framing of Modbus TCP streams (Messaging on TCP/IP V1.0b, 3.1.3), both backends."""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu import FrameKind, MbapError, MbapFrame, MbapFrameList, pdu

# The read of three holding registers from 0x006B at unit 0x11, under transaction 1:
# transaction 00 01, protocol 00 00, length 00 06 (unit id + 5 PDU bytes), unit 11.
REQUEST = bytes.fromhex("0001 0000 0006 11 03 006B 0003")
RESPONSE = bytes.fromhex("0001 0000 0009 11 03 06 022B 0000 0064")
EXCEPTION = bytes.fromhex("0002 0000 0003 11 83 02")


def stream_of(backend: ModuleType, n: int) -> bytes:
    """n ADUs of different sizes (PDU 1 to 253 bytes), transaction ids 0..n-1."""
    out = bytearray()
    for i in range(n):
        size = 1 + (i * 37) % 253
        out += backend.encode_mbap(i, i % 256, bytes([3]) + bytes(range(size - 1)))
    return bytes(out)


def summary(events: list[MbapFrame]) -> list[tuple[object, ...]]:
    return [(e.kind, e.adu, e.offset, e.error) for e in events]


def test_encode_matches_the_header_layout(backend: ModuleType) -> None:
    request = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0x006B, 3)
    assert backend.encode_mbap(1, 0x11, request) == REQUEST
    f = backend.MbapFramer("master")
    assert f.send(1, 0x11, request) == REQUEST
    assert backend.encode_mbap(0xFFFF, 0xFF, b"\x07") == bytes.fromhex("ffff 0000 0002 ff 07")
    big = bytes([0x10]) + bytes(252)
    adu = backend.encode_mbap(7, 1, big)
    assert len(adu) == 260 and adu[4:6] == b"\x00\xfe"


@pytest.mark.parametrize(
    ("args", "exc", "name"),
    [
        ((-1, 1, b"\x03"), ValueError, "transaction"),
        ((65536, 1, b"\x03"), ValueError, "transaction"),
        ((True, 1, b"\x03"), TypeError, "transaction"),
        ((1.0, 1, b"\x03"), TypeError, "transaction"),
        ((1, 256, b"\x03"), ValueError, "unit"),
        ((1, -1, b"\x03"), ValueError, "unit"),
        ((1, "1", b"\x03"), TypeError, "unit"),
        ((1, 1, b""), ValueError, "pdu"),
        ((1, 1, bytes(254)), ValueError, "pdu"),
        ((1, 1, "0300"), TypeError, "pdu"),
    ],
)
def test_encode_rejects_bad_arguments(
    backend: ModuleType, args: tuple[object, object, object], exc: type[Exception], name: str
) -> None:
    with pytest.raises(exc, match=name):
        backend.encode_mbap(*args)
    with pytest.raises(exc, match=name):
        backend.MbapFramer("master").send(*args)


def test_roles_classify_frames(backend: ModuleType) -> None:
    data = REQUEST + RESPONSE + EXCEPTION
    kinds = {
        "slave": [FrameKind.REQUEST] * 3,
        "master": [FrameKind.RESPONSE, FrameKind.RESPONSE, FrameKind.EXCEPTION],
        "monitor": [FrameKind.UNKNOWN, FrameKind.UNKNOWN, FrameKind.EXCEPTION],
    }
    for role, expected in kinds.items():
        f = backend.MbapFramer(role)
        f.receive_data(data)
        events = f.events()
        assert [e.kind for e in events] == expected
        assert [e.kind for e in backend.parse_tcp_stream(data, role)] == expected
    exc = backend.parse_tcp_stream(EXCEPTION, "master")[0]
    assert (exc.transaction, exc.unit, exc.function, exc.exception_code) == (2, 0x11, 0x83, 2)
    resp = backend.parse_tcp_stream(RESPONSE, "master")[0]
    request = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0x006B, 3)
    assert pdu.parse_registers(resp.pdu, 3) == [0x022B, 0, 0x64]
    assert resp.exception_code is None and resp.length == 9 and resp.protocol == 0
    assert backend.parse_tcp_stream(REQUEST, "slave")[0].pdu == request
    with pytest.raises(ValueError, match="role"):
        backend.MbapFramer("client")
    with pytest.raises(ValueError, match="role"):
        backend.parse_tcp_stream(REQUEST, "server")


def test_several_adus_in_one_read(backend: ModuleType) -> None:
    data = stream_of(backend, 40)
    f = backend.MbapFramer("slave")
    f.receive_data(data)  # 40 ADUs, more than the framer's buffer holds at once
    events = f.events()
    assert [e.transaction for e in events] == list(range(40))
    assert b"".join(e.adu for e in events) == data
    assert all(e.error is None and e.kind is FrameKind.REQUEST for e in events)
    assert f.needed == 7 and f.error is None
    assert f.counters["request"] == 40 and f.counters["discard_events"] == 0


def test_split_at_every_byte(backend: ModuleType) -> None:
    data = REQUEST + RESPONSE + backend.encode_mbap(9, 3, bytes([0x10]) + bytes(252)) + EXCEPTION
    whole = backend.MbapFramer("monitor")
    whole.receive_data(data)
    expected = summary(whole.events())
    assert len(expected) == 4
    for cut in range(1, len(data)):
        f = backend.MbapFramer("monitor")
        f.receive_data(data[:cut])
        f.receive_data(data[cut:])
        assert summary(f.events()) == expected, cut
    # and one byte per read, with `needed` right at every step
    f = backend.MbapFramer("monitor")
    got: list[MbapFrame] = []
    for offset_, adu in ((e[2], e[1]) for e in expected):
        for k in range(len(adu)):
            # k bytes of this ADU are in: up to the length field only the header is known
            assert f.needed == (7 - k if k < 6 else len(adu) - k), (offset_, k)
            f.receive_data(adu[k : k + 1])
            got += f.events()
        assert f.needed == 7
    assert summary(got) == expected


def test_needed_follows_the_length_field(backend: ModuleType) -> None:
    f = backend.MbapFramer("slave")
    assert f.needed == 7
    f.receive_data(REQUEST[:5])
    assert f.needed == 2  # header still incomplete: up to the unit id
    f.receive_data(REQUEST[5:6])
    assert f.needed == 6  # length 6 known: 12 bytes in all, 6 here
    f.receive_data(REQUEST[6:11])
    assert f.needed == 1 and f.next_event() is None
    f.receive_data(REQUEST[11:])
    assert f.needed == 7 and f.next_event() is not None


@pytest.mark.parametrize(
    ("header", "reason", "seen"),
    [
        ("0001 0001 0006 11", MbapError.PROTOCOL, 4),  # not Modbus
        ("0001 ffff 0006 11", MbapError.PROTOCOL, 4),
        ("0001 0000 0000 11", MbapError.LENGTH, 6),  # no unit id
        ("0001 0000 0001 11", MbapError.LENGTH, 6),  # unit id without a function code
        ("0001 0000 00ff 11", MbapError.LENGTH, 6),  # PDU of 254 bytes: over 253
        ("0001 0000 0100 11", MbapError.LENGTH, 6),
        ("0001 0000 ffff 11", MbapError.LENGTH, 6),
    ],
)
def test_bad_header_ends_the_stream(
    backend: ModuleType, header: str, reason: MbapError, seen: int
) -> None:
    bad = bytes.fromhex(header) + bytes(20)
    # found as soon as the bytes show it (protocol id after 4 bytes, length after 6)
    f = backend.MbapFramer("slave")
    f.receive_data(REQUEST + bad[: seen - 1])
    assert [e.error for e in f.events()] == [None] and f.error is None
    f.receive_data(bad[seen - 1 : seen])
    (ev,) = f.events()
    assert ev.kind is FrameKind.DISCARD and ev.error is reason
    assert ev.offset == len(REQUEST) and ev.adu == bad[:seen]
    assert f.error is reason and f.needed == 0
    # everything after it is discarded, good ADUs included
    f.receive_data(bad[seen:] + REQUEST)
    assert f.events() == [] and f.error is reason
    assert f.counters[f"discarded_{reason.value}"] == len(bad) + len(REQUEST)
    assert f.counters["request"] == 1 and f.counters["discard_events"] == 1
    # the bulk parser: one discard event for the rest of the capture
    result = backend.parse_tcp_stream(REQUEST + bad + REQUEST, "slave")
    assert [(e.kind, e.error, e.offset) for e in result] == [
        (FrameKind.REQUEST, None, 0),
        (FrameKind.DISCARD, reason, len(REQUEST)),
    ]
    assert result[1].adu == bad + REQUEST
    assert result.counters[f"discarded_{reason.value}"] == len(bad) + len(REQUEST)


def test_extreme_valid_lengths(backend: ModuleType) -> None:
    shortest = bytes.fromhex("0005 0000 0002 01 07")  # FC 07: PDU of one byte
    longest = bytes.fromhex("0006 0000 00fe 01") + bytes([0x17]) + bytes(252)
    result = backend.parse_tcp_stream(shortest + longest, "slave")
    assert [(e.error, len(e.adu)) for e in result] == [(None, 8), (None, 260)]


@pytest.mark.parametrize("cut", [1, 3, 6, 7, 11])
def test_truncated_at_end_of_stream(backend: ModuleType, cut: int) -> None:
    data = RESPONSE + REQUEST[:cut]
    f = backend.MbapFramer("master")
    f.receive_data(data)
    assert len(f.events()) == 1
    assert f.needed == (7 - cut if cut < 6 else len(REQUEST) - cut)
    f.receive_data(b"")  # end of stream
    (ev,) = f.events()
    assert (ev.kind, ev.error, ev.offset, ev.adu) == (
        FrameKind.DISCARD,
        MbapError.TRUNCATED,
        len(RESPONSE),
        REQUEST[:cut],
    )
    assert ev.transaction == (1 if cut >= 2 else -1) and ev.pdu == b""
    assert f.needed == 0 and f.error is None
    f.receive_data(b"")  # a second end is harmless
    with pytest.raises(RuntimeError, match="after the end"):
        f.receive_data(REQUEST)
    result = backend.parse_tcp_stream(data, "master")
    assert [(e.error, e.adu) for e in result] == [
        (None, RESPONSE),
        (MbapError.TRUNCATED, data[9 + 6 :]),
    ]


def test_end_of_stream_between_adus_is_clean(backend: ModuleType) -> None:
    f = backend.MbapFramer("slave")
    f.receive_data(REQUEST)
    f.receive_data(b"")
    assert len(f.events()) == 1 and f.counters["discard_events"] == 0


def test_receive_data_type_errors(backend: ModuleType) -> None:
    f = backend.MbapFramer("slave")
    with pytest.raises(TypeError, match="data"):
        f.receive_data("0001")
    f.receive_data(bytearray(REQUEST[:4]))
    f.receive_data(memoryview(REQUEST)[4:])
    assert len(f.events()) == 1
    with pytest.raises(TypeError, match="data"):
        backend.parse_tcp_stream(12345)


def test_capture_is_lazy_and_grows_in_blocks(backend: ModuleType) -> None:
    adu = bytes.fromhex("0001 0000 0002 01 07")  # 8-byte ADUs: more entries than len // 64
    data = adu * 20_000 + b"\x00\x02\x00"
    result = backend.parse_tcp_stream(data, "slave")
    assert isinstance(result, MbapFrameList)
    assert len(result) == 20_001
    assert result[19_999].offset == 8 * 19_999 and result[19_999].adu == adu
    assert result[-1].error is MbapError.TRUNCATED and result[-1].adu == b"\x00\x02\x00"
    assert [e.offset for e in result[2:4]] == [16, 24]
    assert sum(1 for _ in result.frames()) == 20_000
    assert [e.adu for e in result.errors()] == [b"\x00\x02\x00"]
    assert result.counters["request"] == 20_000 and result.counters["discarded_truncated"] == 3
    with pytest.raises(IndexError):
        result[20_001]
    assert len(backend.parse_tcp_stream(b"")) == 0


def test_capture_index_is_checked_as_a_frame_list_is(backend: ModuleType) -> None:
    # MbapFrameList and FrameList share their sequence part (frames.LazyFrames): a
    # non-integer index is a TypeError naming the list, an index out of range an
    # IndexError naming it, a numpy-style integer (__index__) an index
    result = backend.parse_tcp_stream(bytes.fromhex("0001 0000 0002 01 07") * 3, "slave")
    with pytest.raises(TypeError, match="MbapFrameList indices must be integers or slices"):
        result["1"]
    with pytest.raises(IndexError, match=r"MbapFrameList index 3 out of range \(3 entries\)"):
        result[3]

    class Two:
        def __index__(self) -> int:
            return 2

    assert result[Two()].offset == 16
    assert repr(result) == "<MbapFrameList of 3 entries>"


def test_framer_and_parser_agree(backend: ModuleType) -> None:
    data = stream_of(backend, 25) + bytes.fromhex("0001 0000 0100")
    f = backend.MbapFramer("monitor")
    for i in range(0, len(data), 97):
        f.receive_data(data[i : i + 97])
    f.receive_data(b"")
    framed = summary(f.events())
    parsed = summary(list(backend.parse_tcp_stream(data)))
    assert framed[:25] == parsed[:25]
    # the framer's discard event covers the bytes it held when it saw the bad header
    assert framed[25][3] is parsed[25][3] is MbapError.LENGTH
    assert framed[25][2] == parsed[25][2]
