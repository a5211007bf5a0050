"""parse_stream: the bulk parser, its lazy result and its timestamps (both backends)."""

from __future__ import annotations

import array
from types import ModuleType

import pytest

from pyrtu import ErrorReason, FrameKind, FrameList

REQ = bytes.fromhex("110300000003")
RESP = bytes.fromhex("110306000100020003")


def traffic(backend: ModuleType, n: int) -> bytes:
    return (backend.add_crc(REQ) + backend.add_crc(RESP)) * n


def test_lazy_sequence(backend: ModuleType) -> None:
    data = traffic(backend, 1000) + b"\xff\xfe"
    result = backend.parse_stream(data)
    assert isinstance(result, FrameList)
    assert len(result) == 2001
    assert result[0].kind == FrameKind.REQUEST and result[1].kind == FrameKind.RESPONSE
    assert result[-1].error == ErrorReason.TRUNCATED and result[-1].adu == b"\xff\xfe"
    assert not result[0].error and result[-1].error  # falsy / truthy error attribute
    assert [f.offset for f in result[2:4]] == [19, 27]
    assert sum(1 for _ in result.frames()) == 2000
    assert [f.adu for f in result.errors()] == [b"\xff\xfe"]
    assert result.counters["request"] == 1000 and result.counters["discarded_truncated"] == 2
    with pytest.raises(IndexError):
        result[2001]
    assert result[0].start is None  # no times given


def test_large_result_spans_several_blocks(backend: ModuleType) -> None:
    """More entries than the first output block holds (the C result grows in blocks)."""
    frame = backend.add_crc(bytes.fromhex("0107"))  # 4-byte frames: len(data) // 8 < count
    data = frame * 5000
    result = backend.parse_stream(data, "slave")
    assert len(result) == 5000
    assert result[4999].offset == 4 * 4999 and result[4999].adu == frame


def test_per_byte_times(backend: ModuleType) -> None:
    req, resp = backend.add_crc(REQ), backend.add_crc(RESP)
    char = 11 / 9600
    times = [1.0 + i * char for i in range(len(req))]
    t = times[-1] + 0.010
    times += [t + i * char for i in range(len(resp))]
    result = backend.parse_stream(req + resp, times=times, baudrate=9600)
    assert [f.kind for f in result] == [FrameKind.REQUEST, FrameKind.RESPONSE]
    assert result[1].start == pytest.approx(t - char, abs=2e-6)
    assert result[1].end == pytest.approx(times[-1], abs=2e-6)


def test_chunk_times_and_strict_gaps(backend: ModuleType) -> None:
    req = backend.add_crc(REQ)
    data = req + req
    # second request split by a 3-char gap after 4 bytes: strict discards it
    char = 11 / 9600
    chunks = [(0, 1.0), (8, 1.1), (12, 1.1 + 4 * char + 3 * char)]
    strict = backend.parse_stream(data, chunks=chunks, baudrate=9600, strict=True)
    assert strict[0].error is None
    assert all(f.error for f in strict[1:])
    assert strict[1].error == ErrorReason.T15
    lenient = backend.parse_stream(data, chunks=chunks, baudrate=9600)
    assert [f.adu for f in lenient] == [req, req]


def test_unknown_function_frames_end_at_silence(backend: ModuleType) -> None:
    vendor = backend.add_crc(bytes.fromhex("0a5501020304"))
    req = backend.add_crc(REQ)
    data = vendor + req + vendor
    chunks = [(0, 1.0), (len(vendor), 1.1), (len(vendor) + len(req), 1.2)]
    result = backend.parse_stream(data, chunks=chunks)
    assert [f.adu for f in result] == [vendor, req, vendor]
    assert result[0].kind == FrameKind.UNKNOWN  # monitor: valid CRC, direction unknown
    assert backend.parse_stream(data, "slave", chunks=chunks)[0].kind == FrameKind.REQUEST


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"times": [1.0]}, "times has 1 entries"),
        ({"chunks": [(1, 1.0)]}, "first chunk"),
        ({"chunks": [(0, 1.0), (99, 2.0)]}, "outside"),
        ({"chunks": [(0, 1.0), (4, 2.0), (2, 3.0)]}, "ascend"),
        ({"times": [1.0] * 8, "chunks": [(0, 1.0)]}, "not both"),
        ({"role": "spy"}, "role"),
    ],
)
def test_bad_arguments(backend: ModuleType, kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        backend.parse_stream(backend.add_crc(REQ), **kwargs)


def test_any_bytes_like(backend: ModuleType) -> None:
    req = backend.add_crc(REQ)
    for data in (bytearray(req), memoryview(req), array.array("B", req)):
        assert [f.adu for f in backend.parse_stream(data)] == [req]
    assert len(backend.parse_stream(b"")) == 0
