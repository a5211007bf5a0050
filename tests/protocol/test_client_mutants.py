"""The client protocol's decisions that the mutation run (docs/MUTATION.md) found
untested: which functions go as one `Xfer`, the times it carries, the settling after
a frame that is not the answer, the learned turnaround (its doubling steps and their
cap, one slave's kept while another's is learned), the caches' bounds, the state of
a fresh protocol, the echo mismatch's message, the debug log, the late answer of a
cancelled transaction.  Expected values from the Modbus specifications (answer
lengths, [MB] 6.x; t3.5 and the character time, Serial Line V1.02 2.5.1.1) and the
documented rules, never read back from the protocol; on both backends.
"""

from __future__ import annotations

import logging
import struct
from types import ModuleType
from typing import Any

import pytest

from pyrtu.core.ascii import encode_ascii, make_framer
from pyrtu.core.line import LineConfig
from pyrtu.pdu.errors import BusFault, ExceptionResponseError, FrameError, NoResponseError
from pyrtu.pdu.requests import (
    mask_write_register,
    raw_request,
    read_coils,
    read_discrete_inputs,
    read_holding_registers,
    read_input_registers,
    read_write_registers,
    write_coil,
    write_coils,
    write_register,
    write_registers,
)
from pyrtu.protocol.client import ClientProtocol, ClientState, Done, Send, Wait
from pyrtu.protocol.client_actions import Xfer

LINE = LineConfig(baudrate=9600, parity="N")
#: 8N1: 10 bits a character; t3.5 3.5 characters (Serial Line V1.02 2.5.1.1)
CHAR = LINE.char_time
T35 = LINE.t35_time
FAST = LineConfig(baudrate=115200, parity="N")
FAST_CHAR = FAST.char_time
#: above 19200 baud t3.5 is fixed at 1.75 ms (Serial Line V1.02 2.5.1.1)
FAST_T35 = 0.00175


def crc(backend: ModuleType, body: bytes) -> bytes:
    return bytes(backend.add_crc(body))


def transact(p: ClientProtocol, call: Any, answer: bytes, now: float, split: int = 0) -> Any:
    """One transaction by the steps, sent at ``now``: the answer read whole (or its
    first ``split`` bytes first) t3.5 after the request; the Done."""
    p.start(*call, now=now)
    while p.state is not ClientState.SEND:
        at = p.deadline()
        assert at is not None
        now = max(now, at)
        p.handle_timer(now)
    p.wait_done(b"", now)
    adu = p.data_to_send()
    char = p.line.char_time
    end = now + len(adu) * char
    p.transmitted(end, now)
    t = end + p.line.t35_time + len(answer) * char
    if split:
        p.receive_data(answer[:split], t - (len(answer) - split) * char)
    p.receive_data(answer[split:], t)
    for _ in range(3):  # an answer of no known length ends with the silence after it
        done = p.next_action(t)
        if type(done) is Done:
            return done
        t = done.until
        p.wait_done(b"", t)
    raise AssertionError(f"no answer: {done}")


def run_timers(p: ClientProtocol) -> float:
    """The protocol's timers run until the framer discards the bytes it holds; when."""
    for _ in range(5):
        at = p.deadline()
        assert at is not None
        p.handle_timer(at)
        if p.counters["discarded_bytes"]:
            return at
    raise AssertionError("nothing discarded")


# ----------------------------------------------------------------- Xfer


def _answers(backend: ModuleType) -> list[tuple[Any, bytes]]:
    """A request of each function whose answer's length the request fixes ([MB]
    6.1-6.6, 6.11, 6.12, 6.16, 6.17), and its answer built from the spec."""
    return [
        (read_coils(1, 0, 8), crc(backend, bytes((1, 1, 1, 0x55)))),
        (read_discrete_inputs(1, 0, 8), crc(backend, bytes((1, 2, 1, 0xAA)))),
        (read_holding_registers(1, 0, 2), crc(backend, struct.pack(">BBBHH", 1, 3, 4, 7, 8))),
        (read_input_registers(1, 0, 1), crc(backend, struct.pack(">BBBH", 1, 4, 2, 9))),
        (write_coil(1, 3, True), crc(backend, struct.pack(">BBHH", 1, 5, 3, 0xFF00))),
        (write_register(1, 3, 77), crc(backend, struct.pack(">BBHH", 1, 6, 3, 77))),
        (write_coils(1, 0, [True] * 9), crc(backend, struct.pack(">BBHH", 1, 15, 0, 9))),
        (write_registers(1, 0, [1, 2]), crc(backend, struct.pack(">BBHH", 1, 16, 0, 2))),
        (
            mask_write_register(1, 4, 0x00F2, 0x0025),
            crc(backend, struct.pack(">BBHHH", 1, 22, 4, 0x00F2, 0x0025)),
        ),
        (
            read_write_registers(1, 0, 1, 10, [5]),
            crc(backend, struct.pack(">BBBH", 1, 23, 2, 6)),
        ),
    ]


@pytest.mark.parametrize("index", range(10))
def test_each_function_with_a_fixed_answer_goes_as_one_xfer(
    backend: ModuleType, index: int
) -> None:
    call, answer = _answers(backend)[index]
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    assert transact(p, call, answer, 100.0).error is None
    now = 101.0
    p.start(*call, now=now)
    plan = p.next_action(now, xfer=True)
    assert type(plan) is Xfer, (call, plan)
    assert plan.data == crc(backend, bytes((1,)) + call.pdu)
    assert plan.expect == len(answer) and plan.short_len == 5
    assert plan.send_at <= now and plan.timeout == 2.0


def test_a_function_whose_answer_length_varies_takes_the_steps(backend: ModuleType) -> None:
    # report server id (FC 17, [MB] 6.13): the answer's length is the slave's
    call = raw_request(1, bytes((17,)))
    answer = crc(backend, bytes((1, 17, 3, 0x42, 0xFF, 0x01)))
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    assert transact(p, call, answer, 100.0).error is None
    p.start(*call, now=101.0)
    assert type(p.next_action(101.0, xfer=True)) is not Xfer


@pytest.mark.parametrize(
    ("line", "char", "t35", "early"), [(LINE, CHAR, T35, 0), (FAST, FAST_CHAR, FAST_T35, 1)]
)
def test_the_xfer_first_read_is_t35_plus_turnaround_plus_the_answer(
    backend: ModuleType, line: LineConfig, char: float, t35: float, early: int
) -> None:
    """The first read where the whole answer can be in: t3.5 + the slave's learned
    turnaround + the answer's characters (one fewer on a line faster than 0.5 ms a
    character, where a timed wake-up is late by about one)."""
    p = ClientProtocol(line, timeout=2.0, backend=backend)
    now = _learn(p, 1, 0.004, 100.0)  # an answer of 7 bytes, 4 ms or so past t3.5
    turn = p.turnaround(1)
    assert turn is not None and turn > 0.003
    p.start(*read_holding_registers(1, 0, 1), now=now)
    plan = p.next_action(now, xfer=True)
    assert type(plan) is Xfer
    assert plan.first_wake == pytest.approx(t35 + turn + (7 - early) * char, abs=1e-9)


def test_an_xfer_on_a_quiet_line_is_sent_at_once_early_on_the_clock(backend: ModuleType) -> None:
    """A monotonic clock may read under a second: the send time of a request whose
    line is quiet already is now, not some fixed time."""
    call, answer = _answers(backend)[2]
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    transact(p, call, answer, 0.1)
    now = 0.3
    p.start(*call, now=now)
    assert p.state is ClientState.SEND
    plan = p.next_action(now, xfer=True)
    assert type(plan) is Xfer and plan.send_at <= now


# ------------------------------------------------------ turnaround learning


def _learn(p: ClientProtocol, slave: int, turn: float, now: float) -> float:
    """A transaction to ``slave`` whose answer starts ``turn`` past t3.5, read in two
    parts (so that the turnaround is learned); the time after it."""
    answer = crc(p._backend, struct.pack(">BBBH", slave, 3, 2, 1))
    p.start(*read_holding_registers(slave, 0, 1), now=now)
    while p.state is not ClientState.SEND:
        at = p.deadline()
        assert at is not None
        now = max(now, at)
        p.handle_timer(now)
    p.wait_done(b"", now)
    end = now + 8 * CHAR
    p.transmitted(end, now)
    first = end + T35 + turn + 3 * CHAR  # 3 characters of the answer are in
    p.receive_data(answer[:3], first)
    p.receive_data(answer[3:], first + 4 * CHAR)
    assert p.next_action(first + 4 * CHAR).result() == [1]
    return first + 1.0


def test_learning_a_second_slave_keeps_the_first_slaves_turnaround(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    now = _learn(p, 1, 0.004, 100.0)
    now = _learn(p, 2, 0.009, now)
    one, two = p.turnaround(1), p.turnaround(2)
    assert one == pytest.approx(0.004, abs=1e-9) and two == pytest.approx(0.009, abs=1e-9)


def test_whole_answers_in_first_reads_double_the_step_up_to_4096_times(
    backend: ModuleType,
) -> None:
    """At 9600 baud (a character over 0.5 ms) each whole answer in a first read lowers
    the turnaround by 25 µs, the fourth in a row and each one after by twice the
    one before, up to 4096 x 25 µs (module docstring of client_timing)."""
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    now = _learn(p, 1, 0.5, 100.0)
    call = read_holding_registers(1, 0, 1)
    answer = crc(backend, struct.pack(">BBBH", 1, 3, 2, 1))
    steps = []
    for _ in range(17):
        before = p.turnaround(1)
        assert before is not None
        p.start(*call, now=now)
        plan = p.next_action(now, xfer=True)
        assert type(plan) is Xfer
        end = now + 8 * CHAR
        first_t = end + plan.first_wake
        p.xfer_done(now, end, answer, len(answer), first_t, first_t)
        assert p.next_action(first_t).result() == [1]
        after = p.turnaround(1)
        assert after is not None
        steps.append(round((before - after) / 25e-6))
        now = first_t + 1.0
    assert steps == [1, 1, 1, *(2**k for k in range(1, 13)), 4096, 4096]


def test_a_learned_length_never_wakes_before_the_bytes_needed(backend: ModuleType) -> None:
    """A user function whose answer is address, function and CRC (4 bytes): before any
    byte the framer needs those 4 (an exception answer is longer), the learned length
    is no more: the first sleep lasts t3.5 + turnaround + 4 characters."""
    call = raw_request(1, bytes((0x41,)))
    answer = crc(backend, bytes((1, 0x41)))
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    assert transact(p, call, answer, 100.0).value == b"\x41"
    turn = p.turnaround(1) or 0.0
    p.start(*call, now=101.0)
    p.wait_done(b"", 101.0)
    end = 101.0 + 4 * CHAR
    p.transmitted(end, 101.0)
    action = p.next_action(end)
    assert type(action) is Wait and not action.listen
    assert action.until == pytest.approx(end + T35 + turn + 4 * CHAR, abs=1e-9)


def full_table(backend: ModuleType) -> tuple[ClientProtocol, bytes, float]:
    """A client that learned the answer lengths of 4096 requests (a read of one
    register at each of addresses 0..4095), the answer it had, the time after."""
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    answer = crc(backend, struct.pack(">BBBH", 1, 3, 2, 5))
    now = 100.0
    for address in range(4096):
        transact(p, read_holding_registers(1, address, 1), answer, now)
        now += 0.1
    return p, answer, now


def test_the_answer_lengths_are_remembered_for_4096_requests(backend: ModuleType) -> None:
    """The learned answer lengths are a bounded table: 4096 requests, then it starts
    again (the 4097th request's length is learned in an empty table)."""
    p, answer, now = full_table(backend)
    p.start(*read_holding_registers(1, 0, 1), now=now)
    assert type(p.next_action(now, xfer=True)) is Xfer  # the first still known
    p.abort(now)
    transact(p, read_holding_registers(1, 4096, 1), answer, now)
    now += 0.1
    p.start(*read_holding_registers(1, 0, 1), now=now)
    assert type(p.next_action(now, xfer=True)) is not Xfer  # forgotten
    p.abort(now)
    p.start(*read_holding_registers(1, 4096, 1), now=now + 0.1)
    assert type(p.next_action(now + 0.1, xfer=True)) is Xfer


# ------------------------------------------------ settling, failures, echo


def test_a_fragment_ended_by_silence_settles_for_the_settling_time(backend: ModuleType) -> None:
    """Bytes the framer discards when the line goes quiet (not the answer): the wait
    goes on for the settling time from then, not past the timeout, then FrameError."""
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    p.wait_done(b"", 100.0)
    end = 100.0 + 8 * CHAR
    p.transmitted(end, 100.0)
    p.receive_data(b"\x01\x03", end + 0.01)
    timer = run_timers(p)
    assert p.state is ClientState.ANSWER
    assert p.deadline() == pytest.approx(timer + p.settle, abs=1e-9)
    p.handle_timer(timer + p.settle / 2)
    assert p.state is ClientState.ANSWER
    p.handle_timer(timer + p.settle)
    with pytest.raises(FrameError, match="discarded"):
        p.result()


def test_the_settling_time_never_runs_past_the_timeout(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.015, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    p.wait_done(b"", 100.0)
    end = 100.0 + 8 * CHAR
    p.transmitted(end, 100.0)
    damaged = bytearray(crc(backend, struct.pack(">BBBH", 1, 3, 2, 5)))
    damaged[-1] ^= 0xFF
    p.receive_data(bytes(damaged), end + 0.005)
    assert run_timers(p) < end + 0.015
    assert p.deadline() == pytest.approx(end + 0.015, abs=1e-9)


def test_a_damaged_answer_counts_one_crc_error(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    answer = bytearray(crc(backend, struct.pack(">BBBH", 1, 3, 2, 5)))
    answer[-1] ^= 0xFF
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    p.wait_done(b"", 100.0)
    end = 100.0 + 8 * CHAR
    p.transmitted(end, 100.0)
    p.receive_data(bytes(answer), end + 0.02)
    run_timers(p)  # (a lenient framer waits for the silence after the frame)
    assert p.counters["crc_errors"] == 1


def test_an_echo_mismatch_names_what_was_read_back(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, echo=True, backend=backend)
    call = read_holding_registers(1, 0, 1)
    p.start(*call, now=100.0)
    p.wait_done(b"", 100.0)
    adu = p.data_to_send()
    assert adu == crc(backend, bytes.fromhex("010300000001"))
    end = 100.0 + 8 * CHAR
    p.transmitted(end, 100.0)
    p.receive_data(adu[:3], end)  # the first three come back right
    p.receive_data(b"\x99\x98", end + 0.001)
    with pytest.raises(BusFault) as info:
        p.result()
    sent = " ".join(f"{b:02x}" for b in adu)
    assert str(info.value).endswith(f"sent {sent}, read back 01 03 00 99 98")


def test_an_ascii_exception_answer_without_its_code_has_code_0(backend: ModuleType) -> None:
    line = LineConfig(baudrate=9600, mode="ascii")
    p = ClientProtocol(line, timeout=0.5, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    p.wait_done(b"", 100.0)
    p.transmitted(100.02, 100.0)
    p.receive_data(encode_ascii(b"\x01\x83"), 100.05)
    with pytest.raises(ExceptionResponseError) as info:
        p.result()
    assert info.value.code == 0


# ------------------------------------------------------- a fresh protocol


def test_a_fresh_protocol_defaults(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, backend=backend)
    assert p.retries == 0 and p.late_answer_over_at() == 0.0
    # the framer is the backend's asked for
    assert type(p._core) is type(make_framer(LINE, "master", backend).core)


def test_a_fresh_protocol_sends_at_once_early_on_the_clock(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.2, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=0.5)
    assert p.state is ClientState.SEND


def test_a_timeout_early_on_the_clock_owes_only_the_settling_time(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.2, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=0.1)
    p.wait_done(b"", 0.1)
    end = 0.1 + 8 * CHAR
    p.transmitted(end, 0.1)
    p.handle_timer(end + 0.2)
    with pytest.raises(NoResponseError):
        p.result()
    assert p.late_answer_over_at() == pytest.approx(end + 0.2 + p.settle, abs=1e-9)


# --------------------------------------------------------- a cancelled one


def test_an_abandoned_answer_is_over_a_settling_time_after_its_last_byte(
    backend: ModuleType,
) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    p.wait_done(b"", 100.0)
    end = 100.0 + 8 * CHAR
    p.transmitted(end, 100.0)
    p.abort(end + 0.01)
    # nothing heard since: the abandoned answer's deadline
    assert p.late_answer_over_at() == pytest.approx(end + 0.5, abs=1e-9)
    p.start(*read_holding_registers(1, 0, 1), now=end + 0.02)
    p.receive_data(b"\x01\x03", end + 0.03)  # the late answer, heard
    assert p.late_answer_over_at() == pytest.approx(end + 0.03 + p.settle, abs=1e-9)


def test_an_abandoned_xfer_keeps_the_latest_byte_read(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    transact(p, read_holding_registers(1, 0, 1), crc(backend, b"\x01\x03\x02\x00\x05"), 100.0)
    before = p.last_rx
    p.abandoned_xfer(101.0, 101.01, 101.02)
    assert p.last_rx == 101.01
    # nothing heard since the cancel: the abandoned answer's deadline, timeout after
    # the request's end
    assert p.late_answer_over_at() == pytest.approx(101.5, abs=1e-9)
    p.abandoned_xfer(102.0, 0.0, 102.02)  # nothing read
    assert p.last_rx == 101.01 and before < 101.0


# ------------------------------------------------------------- debug log


def test_the_debug_log_names_the_request_and_the_answer_with_their_times(
    backend: ModuleType, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="pyrtu.drivers.master")
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    call = read_holding_registers(1, 0, 1)
    answer = crc(backend, b"\x01\x03\x02\x00\x05")
    p.start(*call, now=100.0)
    p.wait_done(b"", 100.0)
    end = 100.0 + 0.0125
    p.transmitted(end, 100.0)
    p.receive_data(answer, end + 0.0375)
    assert p.result() == [5]
    adu = crc(backend, bytes.fromhex("010300000001")).hex(" ")
    messages = [r.getMessage() for r in caplog.records]
    assert f"TX slave 1 fc 3: {adu} (12.500 ms on the line)" in messages
    assert f"RX slave 1 fc 3: {answer[:-2].hex(' ')} (37.500 ms)" in messages


# --------------------------------------------------- boundaries and endings


def test_a_request_past_max_adu_names_its_function(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, backend=backend)
    pdu = bytes((16,)) + bytes(253)  # address + 254 + CRC: 257 bytes, max_adu 256
    with pytest.raises(ValueError, match=r"^write_registers: a 257-byte request exceeds max_adu$"):
        p.start(1, pdu, None, 100.0)


def test_a_request_goes_at_exactly_t35_after_the_answer(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    call = read_holding_registers(1, 0, 1)
    done = transact(p, call, crc(backend, b"\x01\x03\x02\x00\x05"), 100.0)
    p.start(*call, now=done.end + T35)
    assert p.state is ClientState.SEND


def test_an_exchange_takes_an_exception_answer_as_its_value(backend: ModuleType) -> None:
    from pyrtu.pdu.requests import exchange

    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    call = exchange(1, bytes.fromhex("0300000001"))
    done = transact(p, call, crc(backend, b"\x01\x83\x02"), 100.0)
    assert done.error is None and done.value == b"\x83\x02" and done.end is not None


def test_a_failed_transaction_has_no_answer_time(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.2, backend=backend)
    call = read_holding_registers(1, 0, 1)
    assert transact(p, call, crc(backend, b"\x01\x03\x02\x00\x05"), 100.0).end is not None
    p.start(*call, now=101.0)
    p.wait_done(b"", 101.0)
    p.transmitted(101.01, 101.0)
    p.handle_timer(101.3)
    done = p.next_action(101.3)
    assert type(done) is Done and isinstance(done.error, NoResponseError) and done.end is None


def _sent(p: ClientProtocol, call: Any, now: float) -> float:
    p.start(*call, now=now)
    p.wait_done(b"", now)
    end = now + len(p.data_to_send()) * CHAR
    p.transmitted(end, now)
    return end


def test_an_answer_framed_by_the_silence_after_the_timeout_still_counts(
    backend: ModuleType,
) -> None:
    """An answer of no known length whose last byte came before the timeout: the
    silence that ends it is past the timeout, the answer is the result."""
    p = ClientProtocol(LINE, timeout=0.1, backend=backend)
    end = _sent(p, raw_request(1, bytes((0x41,))), 100.0)
    p.receive_data(crc(backend, b"\x01\x41\x07"), end + 0.099)
    p.handle_timer(end + 0.2)
    assert p.result() == b"\x41\x07"


def test_bytes_discarded_by_a_silence_after_the_timeout_end_the_attempt(
    backend: ModuleType,
) -> None:
    p = ClientProtocol(LINE, timeout=0.1, backend=backend)
    end = _sent(p, read_holding_registers(1, 0, 1), 100.0)
    p.receive_data(b"\x01\x03", end + 0.099)
    p.handle_timer(end + 0.2)  # the framer drops them, and the attempt is over
    with pytest.raises(FrameError):
        p.result()


def test_at_exactly_half_a_millisecond_a_character_the_xfer_reads_the_whole_answer(
    backend: ModuleType,
) -> None:
    """20000 baud 8N1: a character of exactly 0.5 ms, not shorter: the first read is
    timed for the whole answer (client_timing: faster lines read a character early)."""
    line = LineConfig(baudrate=20000, parity="N")
    assert line.char_time == 0.0005
    call, answer = _answers(backend)[2]
    p = ClientProtocol(line, timeout=2.0, backend=backend)
    transact(p, call, answer, 100.0, split=3)
    turn = p.turnaround(1)
    assert turn is not None
    p.start(*call, now=101.0)
    plan = p.next_action(101.0, xfer=True)
    assert type(plan) is Xfer
    assert plan.first_wake == pytest.approx(0.00175 + turn + len(answer) * 0.0005, abs=1e-9)


def test_a_request_of_exactly_max_adu_is_sent(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, backend=backend)
    pdu = bytes((16,)) + bytes(252)  # address + 253 + CRC: 256 bytes, max_adu
    p.start(1, pdu, None, 100.0)
    assert len(p.data_to_send()) == 256


def test_the_options_are_keywords_only(backend: ModuleType) -> None:
    with pytest.raises(TypeError):
        ClientProtocol(LINE, 0.5)  # type: ignore[misc]
    assert ClientProtocol(LINE, backend=backend).timeout == 1.0


def test_a_turnaround_estimate_below_zero_is_kept_as_zero(backend: ModuleType) -> None:
    """The first bytes of an answer read sooner than t3.5 plus their own characters
    after the request (a slave that does not keep t3.5): the turnaround is 0, not
    negative."""
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    answer = crc(backend, struct.pack(">BBBH", 1, 3, 2, 1))
    end = _sent(p, read_holding_registers(1, 0, 1), 100.0)
    p.receive_data(answer[:3], end + CHAR)
    p.receive_data(answer[3:], end + 5 * CHAR)
    assert p.result() == [1]
    assert p.turnaround(1) == 0.0


def test_an_answer_all_in_the_first_read_of_an_xfer_ends_at_that_read(
    backend: ModuleType,
) -> None:
    """The Xfer's first read brought the whole answer (a later read, nothing): its last
    byte came by the first read, whose time (in whole microseconds) is the answer's."""
    call, answer = _answers(backend)[2]
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    transact(p, call, answer, 100.0)
    p.start(*call, now=101.0)
    plan = p.next_action(101.0, xfer=True)
    assert type(plan) is Xfer
    end = 101.0 + len(plan.data) * CHAR
    first_t = end + plan.first_wake
    p.xfer_done(101.0, end, answer, len(answer), first_t, first_t + 0.01)
    done = p.next_action(first_t + 0.01)
    assert type(done) is Done and done.end == round(first_t * 1_000_000) / 1e6


def test_a_request_after_a_broadcast_without_delay_keeps_t35(backend: ModuleType) -> None:
    """No broadcast turnaround asked for: the next request still waits t3.5 after the
    broadcast's end (frames are separated by t3.5, Serial Line V1.02 2.5.1.1)."""
    p = ClientProtocol(LINE, timeout=0.5, broadcast_delay=0.0, backend=backend)
    end = _sent(p, (0, write_register(0, 3, 7).pdu, None), 100.0)
    assert type(p.next_action(end)) is Done
    p.start(*read_holding_registers(1, 0, 1), now=end)
    assert p.state is ClientState.QUIET
    assert p.deadline() == pytest.approx(end + T35, abs=1e-9)


def test_every_retry_is_sent(backend: ModuleType) -> None:
    """retries=2: the request goes three times before NoResponseError."""
    p = ClientProtocol(LINE, timeout=0.1, retries=2, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=100.0)
    now = 100.0
    for _ in range(3):
        while p.state is ClientState.QUIET:
            at = p.deadline()
            assert at is not None
            now = max(now, at)
            p.handle_timer(now)
        p.wait_done(b"", now)
        end = now + 8 * CHAR
        p.transmitted(end, now)
        now = end + 0.1
        p.handle_timer(now)
    with pytest.raises(NoResponseError):
        p.result()
    c = p.counters
    assert (c["requests"], c["retries"], c["timeouts"]) == (3, 2, 3)


def test_bytes_after_a_broadcasts_echo_are_stale(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, echo=True, backend=backend)
    end = _sent(p, (0, write_register(0, 3, 7).pdu, None), 100.0)
    adu = crc(backend, bytes.fromhex("000600030007"))
    p.receive_data(adu + b"\x55\x66", end + 0.001)  # the echo, then 2 bytes of noise
    assert type(p.next_action(end + 0.001)) is Done
    assert p.counters["discarded_stale"] == 2


# ---------------------------------------- full run of 2026-11-28: boundaries


def test_done_is_true_only_once_the_transaction_is_done(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    assert not p.done
    p.start(*write_register(0, 1, 5), now=10.0)  # a broadcast: no answer awaited
    assert not p.done
    p.wait_done(b"", 10.0)
    assert not p.done
    p.transmitted(10.0 + 8 * CHAR, 10.0)
    assert p.done
    assert p.result() is None
    assert not p.done


def test_a_babbling_line_lets_the_request_go_exactly_at_the_timeout(backend: ModuleType) -> None:
    # t3.5 at 9600 8N1: 3.5 x 10 bits / 9600 (Serial Line V1.02 2.5.1.1)
    t35 = 3.5 * 10 / 9600
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=10.0)  # gives up waiting at 12.0
    p.receive_data(b"\x00", 11.0)  # noise: the silence starts again
    assert p.deadline() == pytest.approx(11.0 + t35, abs=1e-6)  # QUIET: t3.5 after it
    p.receive_data(b"\x00", 11.999)  # its t3.5 ends after 12.0
    assert 11.999 + t35 > 12.0
    assert p.deadline() == 12.0
    p.handle_timer(11.9999)
    assert p.deadline() == 12.0  # still QUIET
    p.handle_timer(12.0)  # exactly at the timeout: send anyway
    assert p.state is ClientState.SEND


def test_a_byte_read_at_the_instant_of_the_abort_is_not_heard_since(backend: ModuleType) -> None:
    # late_answer_over_at: a settling time after a byte heard *since* the abort, else
    # the abandoned answer's deadline (timeout after the request's end)
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=10.0)
    p.wait_done(b"", 10.0)
    p.transmitted(10.01, 10.0)
    p.receive_data(b"\x01", 10.05)  # the answer's first byte
    p.abort(10.05)  # given up on at the same instant
    assert p.late_answer_over_at() == pytest.approx(10.01 + 2.0, abs=1e-9)


@pytest.mark.parametrize(
    ("baudrate", "settle"),
    [
        # docs/POLLER.md: the settling pause is 20 ms or 3 x t3.5, the longer; at 1200
        # 8N1 t3.5 is 3.5 x 10 / 1200 s (29.2 ms, kept in whole microseconds): 87.5 ms
        (1200, 3 * 3.5 * 10 / 1200),
        # at 9600 8N1 3 x t3.5 is 3 x 3.5 x 10 / 9600 s (10.9 ms): 20 ms
        (9600, 0.02),
    ],
)
def test_the_settling_time_is_three_t35_or_20_ms_the_longer(
    backend: ModuleType, baudrate: int, settle: float
) -> None:
    assert max(3 * 3.5 * 10 / baudrate, 0.02) == settle  # the table above, by the rule
    line = LineConfig(baudrate=baudrate, parity="N")
    p = ClientProtocol(line, timeout=2.0, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=10.0)
    p.wait_done(b"", 10.0)
    p.transmitted(10.1, 10.0)
    p.abort(10.2)
    p.receive_data(b"\x01", 10.3)  # heard since the abort
    assert p.late_answer_over_at() == pytest.approx(10.3 + settle, abs=3e-6)


def test_the_framer_timer_does_not_fire_before_its_deadline(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    end = _sent(p, read_holding_registers(1, 0, 1), 10.0)
    p.receive_data(b"\x01\x03\x02", end + 0.05)  # a fragment: 3 of the answer's 7 bytes
    while p.counters["discarded_bytes"] == 0:  # the framer's timers (t3.5, then its flush)
        at = p.deadline()
        assert at is not None and at < end + 2.0  # not the timeout
        p.handle_timer(at - 0.4e-6)  # before the deadline, though it rounds to it in us
        assert p.deadline() == at and p.counters["discarded_bytes"] == 0
        p.handle_timer(at)
    assert p.counters["discarded_bytes"] == 3
    assert p.state is ClientState.ANSWER


def test_a_full_length_table_keeps_its_entries_when_a_known_length_repeats(
    backend: ModuleType,
) -> None:
    """The table of 4096 learned answer lengths starts again only to learn a new
    length: an answer of the length already known changes nothing."""
    p, answer, now = full_table(backend)
    transact(p, read_holding_registers(1, 5, 1), answer, now)  # by the steps, same length
    now += 0.1
    p.start(*read_holding_registers(1, 1, 1), now=now)
    assert type(p.next_action(now, xfer=True)) is Xfer  # another request, still known


def test_next_action_hands_out_an_xfer_only_when_the_driver_says_it_can(
    backend: ModuleType,
) -> None:
    answer = crc(backend, struct.pack(">BBBHH", 1, 3, 4, 7, 8))  # [MB] 6.3
    p = ClientProtocol(LINE, timeout=2.0, backend=backend)
    transact(p, read_holding_registers(1, 0, 2), answer, 100.0)  # its length learned
    p.start(*read_holding_registers(1, 0, 2), now=101.0)
    assert type(p.next_action(101.0)) is Wait  # a look for stale input first
    assert type(p.next_action(101.0, xfer=True)) is Xfer


@pytest.mark.parametrize("mode", ["ascii", "rtu"])
def test_stale_input_just_before_the_request_means_another_look(
    backend: ModuleType, mode: str
) -> None:
    """The look for pending input before the request found stale bytes: the request
    goes only after a look that finds none (ASCII keeps no silence, so the line is
    ready again at once; on RTU the timeout has passed: send anyway)."""
    line = LineConfig(baudrate=9600, parity="N", mode=mode)
    p = ClientProtocol(line, timeout=2.0, backend=backend)
    p.start(*read_holding_registers(1, 0, 1), now=10.0)
    assert p.state is ClientState.SEND
    step = p.next_action(10.0)
    assert type(step) is Wait and step.until == 10.0  # the look for stale input
    at = 10.0 if mode == "ascii" else 12.0  # RTU: at the timeout (see above)
    p.wait_done(b"\x00\x01", at)  # it found some
    assert p.state is ClientState.SEND
    step = p.next_action(at)
    assert type(step) is Wait and step.until == at  # look again
    p.wait_done(b"", at)  # nothing more
    assert type(p.next_action(at)) is Send
