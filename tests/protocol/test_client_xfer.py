"""`ClientProtocol.xfer_done` (an `Xfer`'s report) against the steps it stands
for, on both backends: for every way an answer can come in (split anywhere, whole
in the first read, damaged, another slave's, an exception, too short or too long,
data the decoder refuses), a protocol told with ``xfer_done`` ends exactly where
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
from pyrtu.protocol.client_actions import Xfer

VALUES = list(range(10))
LINES = [LineConfig(baudrate=9600, parity="N"), LineConfig(baudrate=115200, parity="N")]


def _answer(backend: ModuleType, head: bytes = b"\x01\x03\x14") -> bytes:
    body = head + b"".join(v.to_bytes(2, "big") for v in VALUES)
    return bytes(backend.add_crc(body))


def _refuse(pdu: bytes) -> Any:
    raise FrameError("refused")


def _primed(
    backend: ModuleType, line: LineConfig, decode: Any = None
) -> tuple[ClientProtocol, Xfer, float]:
    """A protocol that has seen one answer (by the steps) and started the same
    request again (with ``decode`` in place of its decoder): its `Xfer` and the
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
    plan = p.next_action(t + 0.0001, xfer=True)
    assert type(plan) is Xfer
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
        nxt = p.next_action(done.end or p.last_rx, xfer=True)
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
    """The same xfer reported both ways: (by xfer_done, by the steps, the
    framer's feeds in the first)."""
    out = []
    feeds = 0
    for way in ("xfer_done", "steps"):
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
        if way == "xfer_done":
            p.xfer_done(start, end, data, first_n, first_t, last_t)
        else:
            p.wait_done(b"", start)
            p.transmitted(end, start)
            if first_n:
                p.receive_data(data[:first_n], first_t)
            if len(data) > first_n:
                p.receive_data(data[first_n:], last_t)
        done = _finish(p, last_t)
        out.append(_state(p, done))
        if way == "xfer_done":
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


def _run(
    backend: ModuleType, line: LineConfig, high: float, real: float, count: int
) -> list[float]:
    """``count`` repeated xfers with a slave that answers ``real`` seconds past
    t3.5, the protocol having learned ``high`` (as if from one slow answer): each
    first read at the plan's time gets what has come by then; the turnaround the
    protocol has learned after each."""
    p, plan, _ = _primed(backend, line)
    p._turn[1] = high
    ans = _answer(backend)
    turns = []
    for _ in range(count):
        start = plan.send_at
        end = start + len(plan.data) * line.char_time
        arrive = end + line.t35_time + real + len(ans) * line.char_time  # the real end
        first_t = end + plan.first_wake
        missing = 0 if first_t >= arrive else 1 + int((arrive - first_t) / line.char_time)
        n = max(len(ans) - missing, 0)
        p.xfer_done(start, end, ans, n, max(first_t, end), max(arrive, first_t))
        assert _finish(p, max(arrive, first_t)).result() == VALUES
        turn = p.turnaround(1)
        assert turn is not None
        turns.append(turn)
        p.start(*read_holding_registers(1, 0, 10), now=p.last_rx)
        plan = p.next_action(p.last_rx, xfer=True)
        assert type(plan) is Xfer
    return turns


def test_a_turnaround_learned_too_high_comes_down(backend: ModuleType) -> None:
    """On a slow line the first read is at the answer's predicted end: one slow
    answer must not keep every later read late; whole answers in the first read
    bring the turnaround back down until the reads come early enough to learn it
    again."""
    turns = _run(backend, LINES[0], 0.002, 0.0003, 200)
    assert turns[-1] < 0.0006


@pytest.mark.parametrize("line", LINES, ids=lambda line: str(line.baudrate))
def test_a_turnaround_from_one_slow_answer_comes_down_in_a_few_transactions(
    backend: ModuleType, line: LineConfig
) -> None:
    """A turnaround learned 2 ms too high (a slave's first answer, its thread and
    caches cold: seen on the virtual bus) costs about ten late reads, not a hundred
    (at a quarter character each, 2 ms is 92 steps at 115200): whole answers in the
    first read in a row, after the third, lower it twice as fast each.  Then it
    settles within two characters of the real turnaround."""
    real, char = 0.0003, line.char_time
    turns = _run(backend, line, real + 0.002, real, 120)
    down = next(i for i, t in enumerate(turns) if t <= real + char)
    assert down <= 12, turns[:20]
    assert all(real - char <= t <= real + 2 * char for t in turns[60:]), turns[60:]


def test_an_answer_in_two_reads_ends_the_run_of_faster_steps(backend: ModuleType) -> None:
    """The faster steps are for late reads in a row only: an answer whose first
    read was early (in two reads) starts the count again, so the next whole answer
    lowers the turnaround by one plain step; and a run of any length neither
    overflows the step nor takes the turnaround below 0."""
    line = LINES[1]
    p, _, _ = _primed(backend, line)
    ans = _answer(backend)
    step = line.char_time / 4

    def one(first_n: int) -> float:
        """One xfer of the request started, its first read ``first_n`` bytes
        in; then the next one started; by how much the turnaround came down."""
        before = p.turnaround(1)
        assert before is not None
        start = p.send_at()
        end = start + 8 * line.char_time
        first_t = end + line.t35_time + before + len(ans) * line.char_time
        last_t = first_t + (len(ans) - first_n) * line.char_time
        p.xfer_done(start, end, ans, first_n, first_t, last_t)
        assert _finish(p, last_t).result() == VALUES
        p.start(*read_holding_registers(1, 0, 10), now=last_t)
        assert type(p.next_action(last_t, xfer=True)) is Xfer
        after = p.turnaround(1)
        assert after is not None
        return before - after

    p._turn[1] = 0.01
    lowered = [one(len(ans)) for _ in range(6)]
    assert lowered == pytest.approx([step, step, step, 2 * step, 4 * step, 8 * step])
    one(len(ans) // 2)  # the first read early: learned again
    assert one(len(ans)) == pytest.approx(step)
    # a slave that always answers by the first read: the steps stop growing (the
    # turnaround stays at 0, no step too large for a float)
    for _ in range(1100):
        one(len(ans))
    assert p.turnaround(1) == 0.0
