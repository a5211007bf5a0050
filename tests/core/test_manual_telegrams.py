"""Every worked telegram of the five manuals, through both backends.

The vectors (tests/vectors.py) carry the three errata of the seeds README
corrected, each with a note saying what the manual prints and why.
"""

from __future__ import annotations

import random
from types import ModuleType

import pytest
from vectors import ASCII, RTU, Telegram

import pyrtu
from pyrtu import BONFIGLIOLI, CV100, FrameKind

VENDOR_RULES = {**BONFIGLIOLI, **CV100}
KINDS = {
    "request": FrameKind.REQUEST,
    "response": FrameKind.RESPONSE,
    "exception": FrameKind.EXCEPTION,
}


def _ids(ts: tuple[Telegram, ...]) -> list[str]:
    return [f"{t.source}:{t.where}:{t.kind}"[:80] for t in ts]


@pytest.mark.parametrize("t", RTU, ids=_ids(RTU))
def test_rtu_crc_bytes(backend: ModuleType, t: Telegram) -> None:
    body = t.adu[:-2]
    assert backend.add_crc(body) == t.adu
    assert backend.check_crc(t.adu)
    crc = backend.crc16(body)
    assert bytes((crc & 0xFF, crc >> 8)) == t.adu[-2:]


@pytest.mark.parametrize("t", RTU, ids=_ids(RTU))
def test_rtu_frame_split_and_kind(backend: ModuleType, t: Telegram) -> None:
    """One telegram alone: one frame of the right kind, ending without a timeout."""
    role = "slave" if t.kind == "request" else "master"
    f = backend.Framer(role, baudrate=9600, rules=VENDOR_RULES)
    f.receive_data(t.adu, 10.0)
    ev = f.next_event()
    assert ev is not None, "frame must end by prediction, before any silence"
    assert ev.error is None
    assert ev.adu == t.adu
    assert ev.kind == KINDS[t.kind]
    assert ev.address == t.adu[0] and ev.function == t.adu[1]
    assert ev.pdu == t.adu[1:-2]
    assert f.next_event() is None


@pytest.mark.parametrize("t", ASCII, ids=_ids(ASCII))
def test_ascii_lrc_and_codec(backend: ModuleType, t: Telegram) -> None:
    message = pyrtu.decode_ascii(t.adu)
    assert backend.lrc(message) == int(t.adu[-4:-2], 16)
    assert pyrtu.encode_ascii(message) == t.adu


@pytest.mark.parametrize("t", ASCII, ids=_ids(ASCII))
def test_ascii_framer(t: Telegram) -> None:
    role = "slave" if t.kind == "request" else "master"
    f = pyrtu.core.ascii.AsciiFramer(role)
    for i, byte in enumerate(t.adu):  # one character at a time
        f.receive_data(bytes((byte,)), 1.0 + i * 0.001)
    frame = f.next_event()
    assert frame is not None
    assert frame.error is None and frame.kind == KINDS[t.kind]
    assert frame.message == pyrtu.decode_ascii(t.adu)
    assert frame.pdu == frame.message[1:] and frame.text == frame.wire == t.adu


def test_errata_are_carried_corrected() -> None:
    adus = {t.adu for t in RTU}
    # CFW100/CFW701 FC 43 object 02h: the manuals print 70 77 (CRC of object 00h).
    assert bytes.fromhex("012B0E0102F1B6") in adus
    assert bytes.fromhex("012B0E01027077") not in adus
    # CV100 read deceleration time response: the manual copied the request's CRC.
    assert bytes.fromhex("050302003C4995") in adus
    assert bytes.fromhex("050302003C344F") not in adus
    # ACT/ACU ASCII FC 100 unknown parameter: exception 04, LRC 17 (hex line).
    assert b":01E40417\r\n" in {t.adu for t in ASCII}


def _capture() -> bytes:
    return b"".join(t.adu for t in RTU)


def test_capture_of_all_telegrams_in_monitor_mode(backend: ModuleType) -> None:
    frames = backend.parse_stream(_capture(), "monitor", rules=VENDOR_RULES)
    assert len(frames) == len(RTU)
    for got, t in zip(frames, RTU, strict=True):
        assert got.error is None
        assert got.adu == t.adu
        assert got.kind == KINDS[t.kind], t.where


def test_capture_fed_to_framer_in_random_pieces(backend: ModuleType) -> None:
    """The framer splits the same capture when it arrives in USB-sized bursts."""
    rng = random.Random(7)
    data = _capture()
    f = backend.Framer("monitor", baudrate=19200, rules=VENDOR_RULES)
    pos, now = 0, 100.0
    while pos < len(data):
        step = rng.randint(1, 64)
        f.receive_data(data[pos : pos + step], now)
        pos += step
        now += 0.0005  # bursts closer together than t3.5: only prediction splits them
    f.handle_timer(now + 1.0)
    got = f.events()
    assert [e.adu for e in got] == [t.adu for t in RTU]
    assert [e.kind for e in got] == [KINDS[t.kind] for t in RTU]


@pytest.mark.parametrize("seed", range(12))
def test_bit_flips_never_yield_a_bad_frame(backend: ModuleType, seed: int) -> None:
    rng = random.Random(seed)
    frames = [bytearray(t.adu) for t in RTU]
    touched = set()
    for _ in range(15):
        i = rng.randrange(len(frames))
        bit = rng.randrange(len(frames[i]) * 8)
        frames[i][bit // 8] ^= 1 << (bit % 8)
        touched.add(i)
    data = b"".join(frames)
    result = backend.parse_stream(data, "monitor", rules=VENDOR_RULES)
    good = [f for f in result if f.error is None]
    for f in good:
        assert backend.check_crc(f.adu), f
    assert sum(len(f.adu) for f in result) == len(data)  # every byte accounted for
    # Every untouched telegram is recovered, at its own offset.
    offsets = {f.offset: f.adu for f in good}
    pos = 0
    for i, raw in enumerate(frames):
        if i not in touched:
            assert offsets.get(pos) == bytes(raw), f"telegram {i} at {pos} lost"
        pos += len(raw)
