"""Framer.needed(): the bytes still needed at the head, on both backends.

Driven through every split point of the manuals' telegrams (tests/vectors.py): at
each point the value is a lower bound (the frame never ends sooner by its length),
it is exact once the length is known, and C and the twin agree.
"""

from __future__ import annotations

from types import ModuleType

import pytest
from vectors import RTU, Telegram

from pyrtu import BONFIGLIOLI, CV100

VENDOR_RULES = {**BONFIGLIOLI, **CV100}
CHAR = 11 / 9600


def _ids(ts: tuple[Telegram, ...]) -> list[str]:
    return [f"{t.source}:{t.where}:{t.kind}"[:80] for t in ts]


def _request_before(t: Telegram) -> bytes | None:
    """The request a response telegram answers (it directly precedes it)."""
    i = RTU.index(t)
    if t.kind == "request" or i == 0 or RTU[i - 1].kind != "request":
        return None
    return RTU[i - 1].adu


def _framer(backend: ModuleType, t: Telegram) -> object:
    role = "slave" if t.kind == "request" else "master"
    f = backend.Framer(role, baudrate=9600, rules=VENDOR_RULES)
    request = _request_before(t)
    if request is not None:
        f.send(request)
    return f


def _profile(backend: ModuleType, t: Telegram) -> list[int]:
    """needed() after each byte, one character time apart (byte-timed delivery)."""
    f = _framer(backend, t)
    out = [f.needed()]  # type: ignore[attr-defined]
    now = 10.0
    for i, byte in enumerate(t.adu):
        now += CHAR
        f.receive_data(bytes((byte,)), now)  # type: ignore[attr-defined]
        ev = f.next_event()  # type: ignore[attr-defined]
        if i < len(t.adu) - 1:
            assert ev is None, f"frame ended after {i + 1} of {len(t.adu)} bytes"
        else:
            assert ev is not None and ev.error is None and ev.adu == t.adu
            assert f.next_event() is None  # type: ignore[attr-defined]
        out.append(f.needed())  # type: ignore[attr-defined]
    return out


@pytest.mark.parametrize("t", RTU, ids=_ids(RTU))
def test_needed_at_every_byte(backend: ModuleType, t: Telegram) -> None:
    profile = _profile(backend, t)
    n = len(t.adu)
    # Before the last byte, at least one more byte is needed and never more than
    # the frame still has: a lower bound that a driver may sleep on.
    for k in range(1, n):
        assert 1 <= profile[k] <= n - k, (k, profile)
    # Nothing is lost by the sleep: once known, the bound is the exact rest ...
    assert profile[n - 1] == 1
    known = [k for k in range(1, n) if k + profile[k] == n]
    assert known and known == list(range(known[0], n)), profile
    # ... and it only tightens as bytes arrive.
    ends = [k + profile[k] for k in range(1, n)]
    assert ends == sorted(ends)
    # After the frame: nothing pending (the slave awaits a request, the master
    # got its answer).
    assert profile[n] == 0


@pytest.mark.parametrize("t", RTU, ids=_ids(RTU))
def test_needed_at_every_split_point(backend: ModuleType, t: Telegram) -> None:
    """The frame arrives in two reads, split at each position."""
    n = len(t.adu)
    for k in range(1, n):
        f = _framer(backend, t)
        f.receive_data(t.adu[:k], 10.0)  # type: ignore[attr-defined]
        assert f.next_event() is None  # type: ignore[attr-defined]
        need = f.needed()  # type: ignore[attr-defined]
        assert 1 <= need <= n - k
        f.receive_data(t.adu[k:], 10.0 + (n - k) * CHAR)  # type: ignore[attr-defined]
        ev = f.next_event()  # type: ignore[attr-defined]
        assert ev is not None and ev.adu == t.adu and f.needed() == 0  # type: ignore[attr-defined]


@pytest.mark.parametrize("t", RTU, ids=_ids(RTU))
def test_backends_agree(both: tuple[ModuleType, ModuleType], t: Telegram) -> None:
    c, py = both
    assert _profile(c, t) == _profile(py, t)


def test_master_awaiting_an_answer(backend: ModuleType) -> None:
    """Before the first byte: the shortest answer (an exception response is 5)."""
    cases = {
        "0103000a000a": 5,  # FC 03: 5 + 2 x count, or the exception: 5
        "01050001ff00": 5,  # FC 05: echo of 8 bytes, or an exception of 5
        "0107": 5,  # FC 07: 5 either way
        "0141000a0001": 5,  # CV100 0x41 (vendor rule): 8, or 5
        "015a0001": 4,  # unknown function: the shortest RTU frame
    }
    for hexreq, least in cases.items():
        f = backend.Framer("master", baudrate=19200, rules=VENDOR_RULES)
        assert f.needed() == 0  # nothing sent, nothing pending
        f.send(backend.add_crc(bytes.fromhex(hexreq)))
        assert f.needed() == least, hexreq
    # a broadcast awaits nothing
    f = backend.Framer("master")
    f.send(backend.add_crc(bytes.fromhex("00060001000a")))
    assert f.needed() == 0


def test_exception_answer(backend: ModuleType) -> None:
    f = backend.Framer("master", baudrate=9600)
    f.send(backend.add_crc(bytes.fromhex("0103000a000a")))
    answer = backend.add_crc(bytes.fromhex("018302"))
    got = []
    for i, byte in enumerate(answer):
        f.receive_data(bytes((byte,)), 1.0 + i * CHAR)
        ev = f.next_event()
        got.append((f.needed(), ev is not None))
    # 1 byte: the awaited slave: 5 - 1; 2 bytes: an exception, 5 in all.
    assert got == [(4, False), (3, False), (2, False), (1, False), (0, True)]


def test_unknown_head_is_zero(backend: ModuleType) -> None:
    """A function without a rule ends only by silence: 0, wake on any byte."""
    f = backend.Framer("slave", baudrate=9600)
    f.receive_data(bytes.fromhex("015a0001"), 1.0)
    assert f.next_event() is None
    assert f.needed() == 0


def test_garbage_byte_from_another_address(backend: ModuleType) -> None:
    """One byte that is not the awaited slave's address: 1 (its function decides)."""
    f = backend.Framer("master", baudrate=9600)
    f.send(backend.add_crc(bytes.fromhex("0103000a000a")))
    f.receive_data(b"\x07", 1.0)
    assert f.next_event() is None
    assert f.needed() == 1


def test_frame_after_a_gap_bounds_the_wait(backend: ModuleType) -> None:
    """Lenient mode: an incomplete head, then t3.5 of silence, then the start of a
    frame: the later frame may win, so its smaller need is the bound."""
    f = backend.Framer("master", baudrate=9600)
    f.send(backend.add_crc(bytes.fromhex("0103000a000a")))
    f.receive_data(bytes.fromhex("0103ff"), 1.0)  # claims 255 data bytes: overflow
    f.receive_data(bytes.fromhex("010304"), 1.1)  # after a long silence
    events = []
    while (ev := f.next_event()) is not None:
        events.append(ev)
    need = f.needed()
    # the new head (after the discarded overflow) needs 5 + 4 - 3 = 6 more bytes
    assert need == 6, (events, need)
    f2 = backend.Framer("master", baudrate=9600, max_adu=1024)
    f2.send(backend.add_crc(bytes.fromhex("0103000a000a")))
    f2.receive_data(bytes.fromhex("0103fe"), 1.0)  # 259 bytes: pending in lenient mode
    f2.receive_data(bytes.fromhex("010304"), 1.01)  # t3.5 later (9600 baud: 4 ms)
    assert f2.next_event() is None
    assert f2.needed() == 6


def test_needed_with_line_config(backend: ModuleType) -> None:
    from pyrtu.core.line import LineConfig

    line = LineConfig(baudrate=9600, parity="N", stopbits=2, rules=VENDOR_RULES)
    f = backend.Framer("master", line=line)
    f.send(backend.add_crc(bytes.fromhex("01640001")))  # Bonfiglioli FC 100: 8-byte answer
    f.receive_data(bytes.fromhex("0164"), 1.0)
    assert f.needed() == 6
