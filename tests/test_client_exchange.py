"""`ClientProtocol.exchanged` (an `Exchange`'s report) against the steps it stands
for, on both backends: for every way an answer can come in (split anywhere, whole
in the first read, damaged, another slave's, an exception, too short or too long,
data the decoder refuses), a protocol told with ``exchanged`` ends exactly where
one told with ``wait_done``/``transmitted``/``receive_data`` ends: the same value
or error, counters, times, learned turnaround and next plan.  The answers that are
the request's whole answer take the short cut past the framer (checked here by
counting the framer's feeds), the others the steps."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest

from pyrtu.core.line import LineConfig
from pyrtu.pdu.errors import FrameError
from pyrtu.pdu.requests import read_holding_registers
from pyrtu.protocol.client import ClientProtocol, Done
from pyrtu.protocol.client_actions import Exchange

VALUES = list(range(10))
LINES = [LineConfig(baudrate=9600, parity="N"), LineConfig(baudrate=115200, parity="N")]


def _answer(backend: ModuleType, head: bytes = b"\x01\x03\x14") -> bytes:
    body = head + b"".join(v.to_bytes(2, "big") for v in VALUES)
    return bytes(backend.add_crc(body))


def _refuse(pdu: bytes) -> Any:
    raise FrameError("refused")


def _primed(
    backend: ModuleType, line: LineConfig, decode: Any = None
) -> tuple[ClientProtocol, Exchange, float]:
    """A protocol that has seen one answer (by the steps) and started the same
    request again (with ``decode`` in place of its decoder): its `Exchange` and the
    time it was asked at."""
    p = ClientProtocol(line, timeout=0.5, backend=backend)
    call = read_holding_registers(1, 0, 10)
    p.start(*call, now=100.0)
    p.wait_done(b"", 100.0)
    p.transmitted(100.0 + 8 * line.char_time, 100.0)
    ans = _answer(backend)
    t = 100.0 + (8 + len(ans)) * line.char_time + line.t35_time + 0.0003
    p.receive_data(ans[:6], t - (len(ans) - 6) * line.char_time)
    p.receive_data(ans[6:], t)
    assert p.next_action(t).result() == VALUES
    p.start(call.slave, call.pdu, decode or call.decode, now=t + 0.0001)
    plan = p.next_action(t + 0.0001, exchange=True)
    assert type(plan) is Exchange
    return p, plan, t


def _state(p: ClientProtocol, done: Any) -> tuple[Any, ...]:
    value: Any = None
    error: Any = None
    if done.error is None:
        value = done.value
    else:
        error = (type(done.error), str(done.error))
    nxt = None
    if p.state.value == "idle":
        p.start(*read_holding_registers(1, 0, 10), now=done.end or p.last_rx)
        nxt = p.next_action(done.end or p.last_rx, exchange=True)
        p.abort(p.last_rx)
    return (
        value,
        error,
        done.end,
        dict(p.counters),
        p.tx_end,
        p.last_rx,
        p.answer_end,
        p.failed_at,
        p.turnaround(1),
        nxt,
    )


def _finish(p: ClientProtocol, now: float) -> Any:
    """Run the protocol's own waits to the end (no more input comes)."""
    for _ in range(100):
        action = p.next_action(now)
        if type(action) is Done:
            return action
        now = max(now, getattr(action, "until", now))
        p.wait_done(b"", now)
    raise AssertionError("the protocol never ended")


def _both(
    backend: ModuleType,
    line: LineConfig,
    data: bytes,
    first_n: int,
    late: float = 0.0,
    decode: Any = None,
) -> tuple[tuple[Any, ...], tuple[Any, ...], int]:
    """The same exchange reported both ways: (by exchanged, by the steps, the
    framer's feeds in the first)."""
    out = []
    feeds = 0
    for way in ("exchanged", "steps"):
        p, plan, _ = _primed(backend, line, decode)
        core = p._core
        fed = [0]
        real_feed = core.feed

        def counting(chunk: bytes, now_us: int, real: Any = real_feed, fed: Any = fed) -> int:
            fed[0] += 1
            return int(real(chunk, now_us))

        core.feed = counting  # type: ignore[method-assign]
        start = plan.send_at
        end = start + len(plan.data) * line.char_time
        first_t = end + plan.first_wake + late
        last_t = first_t + (len(data) - first_n) * line.char_time
        if way == "exchanged":
            p.exchanged(start, end, data, first_n, first_t, last_t)
        else:
            p.wait_done(b"", start)
            p.transmitted(end, start)
            if first_n:
                p.receive_data(data[:first_n], first_t)
            if len(data) > first_n:
                p.receive_data(data[first_n:], last_t)
        done = _finish(p, last_t)
        out.append(_state(p, done))
        if way == "exchanged":
            feeds = fed[0]
    return out[0], out[1], feeds


@pytest.mark.parametrize("line", LINES, ids=lambda line: str(line.baudrate))
def test_a_whole_answer_ends_as_the_steps_end_it(backend: ModuleType, line: LineConfig) -> None:
    ans = _answer(backend)
    for first_n in range(len(ans) + 1):
        for late in (0.0, 0.0004, -0.0002):
            fast, steps, feeds = _both(backend, line, ans, first_n, late)
            assert fast == steps, (first_n, late)
            assert fast[0] == VALUES and feeds == 0, (first_n, late)


@pytest.mark.parametrize("line", LINES, ids=lambda line: str(line.baudrate))
def test_anything_else_takes_the_steps(backend: ModuleType, line: LineConfig) -> None:
    ans = _answer(backend)
    damaged = bytes([ans[0], ans[1], ans[2], ans[3] ^ 0x10]) + ans[4:]
    cases = {
        "crc": (damaged, None),
        "another slave": (_answer(backend, b"\x02\x03\x14"), None),
        "another function": (_answer(backend, b"\x01\x04\x14"), None),
        "refused by the decoder": (ans, _refuse),
        "exception": (bytes(backend.add_crc(b"\x01\x83\x02")), None),
        "short": (ans[:-3], None),
        "long": (ans + b"\x00", None),  # (the framer takes the answer, the rest is left)
        "nothing": (b"", None),
    }
    for name, (data, decode) in cases.items():
        for first_n in sorted({0, 1, len(data) // 2, len(data)}):
            fast, steps, feeds = _both(backend, line, data, first_n, decode=decode)
            assert fast == steps, (name, first_n)
            assert (fast[0] == VALUES) == (name == "long"), name
            assert feeds > 0 or not data, name


def test_a_turnaround_learned_too_high_comes_down(backend: ModuleType) -> None:
    """On a slow line the first read is at the answer's predicted end: one slow
    answer must not keep every later read late; whole answers in the first read
    bring the turnaround back down (`WAKE_STEP` each) until the reads come early
    enough to learn it again."""
    line = LINES[0]
    p, plan, _ = _primed(backend, line)
    p._turn[1] = 0.002  # as if one answer had come 2 ms late
    ans = _answer(backend)
    turns = []
    for _ in range(200):
        start = plan.send_at
        end = start + len(plan.data) * line.char_time
        arrive = end + line.t35_time + 0.0003 + len(ans) * line.char_time  # the real end
        first_t = end + plan.first_wake
        missing = 0 if first_t >= arrive else 1 + int((arrive - first_t) / line.char_time)
        n = max(len(ans) - missing, 0)
        p.exchanged(start, end, ans, n, max(first_t, end), max(arrive, first_t))
        assert _finish(p, max(arrive, first_t)).result() == VALUES
        turns.append(p.turnaround(1))
        p.start(*read_holding_registers(1, 0, 10), now=p.last_rx)
        plan = p.next_action(p.last_rx, exchange=True)
        assert type(plan) is Exchange
    assert turns[-1] is not None and turns[-1] < 0.0006
