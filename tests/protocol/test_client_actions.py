"""The client protocol's actions (`next_action`: Send / Wait / Done) with synthetic
time, on both backends: the decisions a driver no longer makes (a look for stale
input before the request, a sleep on the answer's predicted length, a wait for
input until the deadline, the sleep to the send time) and what `Done` carries."""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu.core.line import LineConfig
from pyrtu.pdu.errors import ExceptionResponseError, NoResponseError
from pyrtu.pdu.requests import read_holding_registers, write_register
from pyrtu.protocol.client import ClientProtocol, ClientState, Done, Send, Wait
from pyrtu.protocol.client_actions import Xfer

LINE = LineConfig(baudrate=9600, parity="N")
CHAR, T35 = LINE.char_time, LINE.t35_time
VALUES = list(range(10))


def answer(backend: ModuleType) -> bytes:
    body = bytes((1, 3, 20)) + b"".join(v.to_bytes(2, "big") for v in VALUES)
    return bytes(backend.add_crc(body))


def started(backend: ModuleType, line: LineConfig = LINE, **kw: object) -> ClientProtocol:
    p = ClientProtocol(line, timeout=0.5, backend=backend, **kw)  # type: ignore[arg-type]
    p.start(*read_holding_registers(1, 0, 10), now=100.0)
    return p


def send(p: ClientProtocol, now: float) -> float:
    """The look for stale input, then the request: its end."""
    assert p.next_action(now) == Wait(now, False, 0)  # read what is pending, no wait
    p.wait_done(b"", now)
    action = p.next_action(now)
    assert type(action) is Send
    end = now + len(action.data) * CHAR
    p.transmitted(end, now)
    return end


def test_a_transaction_as_actions(backend: ModuleType) -> None:
    p = started(backend)
    end = send(p, 100.0)
    # a timed line: sleep until the answer's first bytes can be in (t3.5 + 5 chars)
    nap = p.next_action(end)
    assert nap == Wait(pytest.approx(end + T35 + 5 * CHAR), False, 5)
    ans = answer(backend)
    t = end + T35 + 5 * CHAR
    p.wait_done(ans[:5], t)
    # the rest but its last byte is predicted (20 needed): sleep on it
    assert p.next_action(t) == Wait(pytest.approx(t + 19 * CHAR), False, 20)
    t += 19 * CHAR
    p.wait_done(ans[5:-1], t)
    # one byte needed: no sleep, listen for it (it is read as it comes, so the next
    # silence counts from the answer's real end), until the framer's silence timer
    assert p.next_action(t) == Wait(pytest.approx(t + T35, abs=5e-5), True, 1)
    p.wait_done(ans[-1:], t + CHAR)
    done = p.next_action(t + CHAR)
    assert done == Done(VALUES, None, pytest.approx(t + CHAR))
    assert done.result() == VALUES and p.state is ClientState.IDLE
    with pytest.raises(RuntimeError, match="no transaction"):
        p.next_action(t + CHAR)


def test_stale_input_before_the_request_restarts_the_silence(backend: ModuleType) -> None:
    p = started(backend)
    assert p.next_action(100.0) == Wait(100.0, False, 0)
    p.wait_done(b"\x01\x02", 100.001)  # a late answer, noise: not the request's turn
    assert p.counters["discarded_stale"] == 2
    quiet = p.next_action(100.001)
    assert quiet == Wait(pytest.approx(100.001 + T35), False, 0)  # a sleep to the send time
    p.wait_done(b"", quiet.until)  # woke at the send time, nothing came: send at once
    assert type(p.next_action(quiet.until)) is Send


def test_an_untimed_line_waits_for_input_at_once(backend: ModuleType) -> None:
    p = started(backend, LineConfig(baudrate=9600, parity="N", t35=0))
    end = send(p, 100.0)
    assert p.next_action(end) == Wait(end + 0.5, True, 5)  # no sleep on the prediction


def test_done_carries_the_error_and_no_end(backend: ModuleType) -> None:
    p = started(backend)
    end = send(p, 100.0)
    p.wait_done(b"", end + 0.5)  # the deadline: no answer
    done = p.next_action(end + 0.5)
    assert type(done) is Done and done.end is None
    assert isinstance(done.error, NoResponseError)
    with pytest.raises(NoResponseError):
        done.result()
    p.start(*read_holding_registers(1, 0, 10), now=end + 0.5)
    end = send(p, max(end + 0.5 + p.settle, p.send_at()))
    p.wait_done(bytes(backend.add_crc(b"\x01\x83\x02")), end + T35 + 5 * CHAR)
    done = p.next_action(end + 0.1)
    assert isinstance(done, Done) and isinstance(done.error, ExceptionResponseError)
    assert done.end is None


def test_a_broadcast_is_done_after_the_write(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    p.start(*write_register(0, 1, 5), now=100.0)
    send(p, 100.0)
    assert p.next_action(100.01) == Done(None, None, None)
    # the turnaround delay before the next request is a sleep
    p.start(*read_holding_registers(1, 0, 10), now=100.02)
    assert p.next_action(100.02) == Wait(pytest.approx(100.0 + 8 * CHAR + 0.1), False, 0)


def test_an_echo_is_slept_on_then_the_answer(backend: ModuleType) -> None:
    p = started(backend, echo=True)
    end = send(p, 100.0)
    wake = p.next_action(end)
    assert type(wake) is Wait and not wake.listen and wake.until > end
    p.wait_done(bytes(backend.add_crc(bytes.fromhex("01030000000a"))), wake.until)
    assert p.counters["echo_mismatches"] == 0 and p.state is ClientState.ANSWER


def test_a_repeated_request_is_offered_as_one_xfer(backend: ModuleType) -> None:
    """A driver that asks gets an `Xfer` for a request whose answer it has seen:
    the protocol's own times (t3.5 after the answer, the first read at the learned
    answer's end on this slow line), its length and the exception's; reported
    through the usual inputs, the transaction ends as the steps would end it."""
    p = started(backend)
    assert type(p.next_action(100.0, xfer=True)) is Wait  # no answer length learned yet
    end = send(p, 100.0)
    ans = answer(backend)
    t = end + T35 + len(ans) * CHAR
    p.wait_done(ans, t)
    assert p.next_action(t).result() == VALUES
    p.start(*read_holding_registers(1, 0, 10), now=t)
    plan = p.next_action(t, xfer=True)
    assert type(plan) is Xfer
    assert plan.data == p.encode(1, read_holding_registers(1, 0, 10).pdu)
    assert plan.send_at == pytest.approx(t + T35)  # t3.5 after the answer's last byte
    turn = p.turnaround(1) or 0.0
    assert plan.first_wake == pytest.approx(T35 + turn + len(ans) * CHAR)
    assert (plan.timeout, plan.expect, plan.short_len) == (0.5, len(ans), 5)
    # stale input at the send time: nothing sent, the silence starts again
    p.wait_done(b"\x00\x01", plan.send_at)
    again = p.next_action(plan.send_at, xfer=True)
    assert type(again) is Xfer
    assert again.send_at == pytest.approx(plan.send_at + T35)
    assert p.counters["discarded_stale"] == 2
    # sent at that time, the answer in two reads
    start = again.send_at
    p.wait_done(b"", start)
    stop = start + 8 * CHAR
    p.transmitted(stop, start)
    first = stop + again.first_wake
    p.receive_data(ans[:-1], first)
    p.receive_data(ans[-1:], first + CHAR)
    done = p.next_action(first + CHAR, xfer=True)
    assert type(done) is Done and done.result() == VALUES
    assert done.end == pytest.approx(first + CHAR, abs=1e-6)


def test_an_xfer_reads_a_character_early_on_a_fast_line(backend: ModuleType) -> None:
    """Above 19200 baud a timed wake-up is typically a character late: the first read
    is planned a character before the learned answer's end (at it on a slow line)."""
    fast = LineConfig(baudrate=115200, parity="N")
    p = started(backend, fast)
    end = send(p, 100.0)
    ans = answer(backend)
    t = end + fast.t35_time + len(ans) * fast.char_time
    p.wait_done(ans, t)
    assert p.next_action(t).result() == VALUES
    p.start(*read_holding_registers(1, 0, 10), now=t)
    plan = p.next_action(t, xfer=True)
    assert type(plan) is Xfer
    turn = p.turnaround(1) or 0.0
    want = fast.t35_time + turn + (len(ans) - 1) * fast.char_time
    assert plan.first_wake == pytest.approx(want)


def test_no_xfer_where_it_does_not_apply(backend: ModuleType) -> None:
    """ASCII, an echo, strict framing, a line without timing, a broadcast: the steps."""
    for line, kw in (
        (LINE.replace(mode="ascii"), {}),
        (LINE, {"echo": True}),
        (LINE.replace(strict=True), {}),
        (LineConfig(baudrate=9600, parity="N", t35=0), {}),
    ):
        p = ClientProtocol(line, timeout=0.5, backend=backend, **kw)  # type: ignore[arg-type]
        p._sizes[p.encode(1, read_holding_registers(1, 0, 10).pdu)] = 25
        p.start(*read_holding_registers(1, 0, 10), now=100.0)
        assert type(p.next_action(100.0, xfer=True)) is not Xfer, line
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    call = write_register(0, 1, 7)
    p.start(*call, now=100.0)  # a broadcast: no answer awaited
    assert type(p.next_action(100.0, xfer=True)) is not Xfer
