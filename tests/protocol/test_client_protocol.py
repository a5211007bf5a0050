"""The sans-I/O client protocol driven with synthetic time: no port, no sleep.

Every path of a transaction: normal, exception, timeout, retry, late answer, echo and
echo mismatch, broadcast, ASCII, garbage before the answer, the answer split at every
byte boundary, and needed() at every step; on both backends.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest

from pyrtu import pdu as pdus
from pyrtu.core.ascii import encode_ascii
from pyrtu.core.line import LineConfig
from pyrtu.pdu.errors import BusFault, ExceptionResponseError, FrameError, NoResponseError
from pyrtu.pdu.requests import read_holding_registers, write_register
from pyrtu.protocol.client import ClientProtocol, ClientState
from pyrtu.protocol.client_timing import WAKE_STEP

LINE = LineConfig(baudrate=9600, parity="N")  # char 1042 us, t3.5 3646 us
CHAR = LINE.char_time
T35 = LINE.t35_time


def proto(backend: ModuleType, line: LineConfig = LINE, **kw: Any) -> ClientProtocol:
    kw.setdefault("timeout", 0.5)
    return ClientProtocol(line, backend=backend, **kw)


def regs(backend: ModuleType, slave: int, values: list[int]) -> bytes:
    body = bytes((slave, 3, 2 * len(values))) + b"".join(v.to_bytes(2, "big") for v in values)
    return bytes(backend.add_crc(body))


def send(p: ClientProtocol, now: float) -> tuple[bytes, float]:
    """Run QUIET -> SEND at ``now`` (or at the protocol's send time); transmit."""
    if p.state is ClientState.QUIET:
        at = p.deadline()
        assert at is not None
        now = max(now, at)
        p.handle_timer(now)
    assert p.state is ClientState.SEND
    adu = p.data_to_send()
    end = now + len(adu) * CHAR
    p.transmitted(end, now)
    return adu, end


def feed_bytes(p: ClientProtocol, data: bytes, t: float) -> tuple[list[int], float]:
    """One byte per character time; needed() after each."""
    seen = []
    for byte in data:
        t += CHAR
        p.receive_data(bytes((byte,)), t)
        seen.append(p.needed())
    return seen, t


def test_normal_transaction_and_needed_at_every_byte(backend: ModuleType) -> None:
    p = proto(backend)
    call = read_holding_registers(1, 0, 10)
    p.start(*call, now=100.0)
    assert p.state is ClientState.SEND and p.needed() == 0
    adu, end = send(p, 100.0)
    assert adu == backend.add_crc(bytes.fromhex("01030000000a"))
    assert p.state is ClientState.ANSWER and p.deadline() == pytest.approx(end + 0.5)
    assert p.needed() == 5  # the answer is at least an exception response's 5 bytes
    answer = regs(backend, 1, list(range(10)))
    seen, t = feed_bytes(p, answer, end + T35)
    # 1 byte: the awaited slave, 4 more; 2: function 3, the byte count decides;
    # 3 bytes: the count is in: 25 - 3, then down one by one.
    assert seen == [4, 3, *range(22, 0, -1), 0]
    assert p.state is ClientState.DONE and p.result() == list(range(10))
    assert p.answer_end == pytest.approx(t)
    c = p.counters
    assert c["requests"] == c["responses"] == 1 and c["discarded_bytes"] == 0
    # the next request keeps t3.5 after the answer's last byte
    p.start(*call, now=t)
    assert p.state is ClientState.QUIET and p.deadline() == pytest.approx(t + T35)


def test_answer_split_at_every_byte_boundary(backend: ModuleType) -> None:
    answer = regs(backend, 1, [7, 8, 9])
    for k in range(1, len(answer)):
        p = proto(backend)
        p.start(*read_holding_registers(1, 0, 3), now=10.0)
        _adu, end = send(p, 10.0)
        p.receive_data(answer[:k], end + 0.01)
        assert p.state is ClientState.ANSWER
        assert 1 <= p.needed() <= len(answer) - k
        p.receive_data(answer[k:], end + 0.02)
        assert p.result() == [7, 8, 9]


def test_exception_response(backend: ModuleType) -> None:
    p = proto(backend)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    _adu, end = send(p, 1.0)
    p.receive_data(backend.add_crc(bytes.fromhex("018302")), end + 0.01)
    with pytest.raises(ExceptionResponseError) as info:
        p.result()
    assert info.value.code == 2 and p.counters["exceptions"] == 1
    # answered: the next request needs only t3.5, no settling
    p.start(*read_holding_registers(1, 0, 2), now=end + 0.01)
    assert p.deadline() == pytest.approx(end + 0.01 + T35)


def test_timeout(backend: ModuleType) -> None:
    p = proto(backend, timeout=0.2)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    _adu, end = send(p, 1.0)
    p.handle_timer(end + 0.1)
    assert p.state is ClientState.ANSWER
    assert p.deadline() == pytest.approx(end + 0.2)
    p.handle_timer(end + 0.2)
    with pytest.raises(NoResponseError, match=r"no response within 0\.2 s"):
        p.result()
    assert p.counters["timeouts"] == 1 and p.counters["retries"] == 0
    # a late answer may still come: the next request waits the settling time
    p.start(*read_holding_registers(1, 0, 2), now=end + 0.2)
    assert p.deadline() == pytest.approx(end + 0.2 + p.settle)


def test_retry_after_timeout(backend: ModuleType) -> None:
    p = proto(backend, timeout=0.2, retries=2)
    p.start(*read_holding_registers(1, 0, 1), now=1.0)
    first, end = send(p, 1.0)
    p.handle_timer(end + 0.2)
    assert p.state is ClientState.QUIET and p.counters["retries"] == 1
    second, end2 = send(p, end + 0.2)
    assert second == first and end2 >= end + 0.2 + p.settle
    p.receive_data(regs(backend, 1, [42]), end2 + 0.01)
    assert p.result() == [42]
    c = p.counters
    assert c["requests"] == 2 and c["timeouts"] == 1 and c["responses"] == 1


def test_retries_exhausted(backend: ModuleType) -> None:
    p = proto(backend, timeout=0.1, retries=1)
    p.start(*read_holding_registers(1, 0, 1), now=1.0)
    _adu, end = send(p, 1.0)
    p.handle_timer(end + 0.1)
    _adu, end = send(p, end + 0.1)
    p.handle_timer(end + 0.1)
    with pytest.raises(NoResponseError):
        p.result()
    assert p.counters["retries"] == 1 and p.counters["timeouts"] == 2


def test_late_answer_is_stale_or_unexpected(backend: ModuleType) -> None:
    p = proto(backend, timeout=0.1)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    _adu, end = send(p, 1.0)
    p.handle_timer(end + 0.1)
    with pytest.raises(NoResponseError):
        p.result()
    # the late answer (2 registers) arrives before the next request: stale
    late = regs(backend, 1, [1, 2])
    p.start(*read_holding_registers(1, 0, 3), now=end + 0.11)
    p.receive_data(late, end + 0.115)
    assert p.state is ClientState.QUIET and p.counters["discarded_stale"] == len(late)
    assert p.deadline() == pytest.approx(end + 0.115 + p.settle)  # restarts the silence
    _adu, end2 = send(p, end + 0.115)
    # another late answer after the request: a valid frame that is not the answer
    p.receive_data(late, end2 + 0.01)
    assert p.state is ClientState.ANSWER and p.counters["discarded_unexpected"] == len(late)
    assert p.deadline() == pytest.approx(end2 + 0.01 + p.settle)  # settling, not timeout
    p.receive_data(regs(backend, 1, [4, 5, 6]), end2 + 0.02)
    assert p.result() == [4, 5, 6]


def test_not_the_answer_ends_in_a_frame_error_after_settling(backend: ModuleType) -> None:
    cases = [
        (regs(backend, 2, [5]), "from slave 2"),
        (backend.add_crc(bytes.fromhex("0104020005")), "function 0x04"),
        (regs(backend, 1, [1, 2, 3]), "PDU has 8 bytes, expected 4"),
    ]
    for frame, message in cases:
        p = proto(backend)
        p.start(*read_holding_registers(1, 0, 1), now=1.0)
        _adu, end = send(p, 1.0)
        p.receive_data(frame, end + 0.01)
        assert p.deadline() == pytest.approx(end + 0.01 + p.settle)
        p.handle_timer(end + 0.01 + p.settle)
        with pytest.raises(FrameError, match=message):
            p.result()
        assert p.counters["frame_errors"] == 1
        assert p.counters["discarded_unexpected"] == len(frame)


def test_garbage_before_the_answer(backend: ModuleType) -> None:
    p = proto(backend)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    _adu, end = send(p, 1.0)
    garbage = b"\x00\xff"
    p.receive_data(garbage + regs(backend, 1, [3, 4]), end + 0.01)
    # no length fits the head: the silence after the burst delimits it
    assert p.state is ClientState.ANSWER and p.needed() == 0
    assert p.deadline() == pytest.approx(end + 0.01 + T35)
    p.handle_timer(end + 0.01 + T35)
    assert p.result() == [3, 4]
    assert p.counters["discarded_bytes"] == len(garbage)


def test_corrupted_answer(backend: ModuleType) -> None:
    p = proto(backend)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    _adu, end = send(p, 1.0)
    bad = bytearray(regs(backend, 1, [3, 4]))
    bad[4] ^= 1
    p.receive_data(bytes(bad), end + 0.01)
    while p.state is ClientState.ANSWER:
        at = p.deadline()
        assert at is not None
        p.handle_timer(at)
    with pytest.raises(FrameError, match="crc"):
        p.result()
    assert p.counters["crc_errors"] >= 1


def test_echo(backend: ModuleType) -> None:
    p = proto(backend, echo=True)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    adu, end = send(p, 1.0)
    assert p.needed() == len(adu) + 5
    p.receive_data(adu[:3], end)
    assert p.needed() == len(adu) - 3 + 5
    p.receive_data(adu[3:] + regs(backend, 1, [1, 2]), end + 0.01)
    assert p.result() == [1, 2]
    assert p.counters["echo_mismatches"] == 0


def test_echo_mismatch_and_missing_echo(backend: ModuleType) -> None:
    p = proto(backend, echo=True)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    adu, end = send(p, 1.0)
    p.receive_data(adu[:2] + b"\xff", end)
    with pytest.raises(BusFault, match="echo mismatch"):
        p.result()
    # the next transaction settles first (the slave may answer the garbled request)
    p.start(*read_holding_registers(1, 0, 2), now=end)
    assert p.deadline() == pytest.approx(end + p.settle)
    adu, end = send(p, end)
    p.handle_timer(end + 0.5)
    with pytest.raises(BusFault, match="did not come back"):
        p.result()
    assert p.counters["echo_mismatches"] == 2


def test_broadcast(backend: ModuleType) -> None:
    p = proto(backend, broadcast_delay=0.1)
    p.start(*write_register(0, 5, 6), now=1.0)
    adu, end = send(p, 1.0)
    assert adu == backend.add_crc(bytes.fromhex("000600050006"))
    assert p.state is ClientState.DONE and p.result() is None
    assert p.counters["broadcasts"] == 1 and p.counters["responses"] == 0
    p.start(*read_holding_registers(1, 0, 1), now=end)
    assert p.deadline() == pytest.approx(end + 0.1)  # the turnaround delay


def test_broadcast_with_echo(backend: ModuleType) -> None:
    p = proto(backend, echo=True)
    p.start(*write_register(0, 5, 6), now=1.0)
    adu, end = send(p, 1.0)
    assert p.state is ClientState.ANSWER and p.needed() == len(adu)
    p.receive_data(adu, end)
    assert p.result() is None


def test_ascii(backend: ModuleType) -> None:
    line = LineConfig(mode="ascii", parity="N")
    p = proto(backend, line=line)
    assert p.gap == 0
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    adu, end = send(p, 1.0)
    assert adu == encode_ascii(bytes.fromhex("010300000002"))
    answer = encode_ascii(bytes.fromhex("01030400070008"))
    p.receive_data(b"junk" + answer[:5], end + 0.01)
    assert p.state is ClientState.ANSWER
    p.receive_data(answer[5:], end + 0.02)
    assert p.result() == [7, 8]
    p.start(*read_holding_registers(1, 0, 2), now=end + 0.02)
    _adu, end = send(p, end + 0.02)
    p.receive_data(encode_ascii(bytes.fromhex("018302")), end + 0.01)
    with pytest.raises(ExceptionResponseError):
        p.result()


def test_abort_makes_the_next_transaction_wait(backend: ModuleType) -> None:
    p = proto(backend)
    p.start(*read_holding_registers(1, 0, 1), now=1.0)
    _adu, end = send(p, 1.0)
    p.abort(end + 0.05)
    assert p.state is ClientState.IDLE
    p.start(*read_holding_registers(1, 0, 1), now=end + 0.05)
    assert p.deadline() == pytest.approx(end + 0.05 + p.settle)


def test_misuse_is_refused(backend: ModuleType) -> None:
    p = proto(backend)
    with pytest.raises(RuntimeError):
        p.data_to_send()
    with pytest.raises(RuntimeError):
        p.result()
    p.start(*read_holding_registers(1, 0, 1), now=1.0)
    with pytest.raises(RuntimeError, match="in progress"):
        p.start(*read_holding_registers(1, 0, 1), now=1.0)
    big = pdus.write_registers_request(0, [1] * 123)
    q = proto(backend, line=LineConfig(max_adu=64))
    with pytest.raises(ValueError, match="max_adu"):
        q.start(1, big, None, 1.0)
    assert q.state is ClientState.IDLE and q.counters["requests"] == 0


def test_ready_at_learns_the_slaves_turnaround(backend: ModuleType) -> None:
    """The first sleep of an answer starts after the slave's learned turnaround: a
    slave that answers 2 ms past t3.5 is first read when its first bytes are in,
    not 2 ms early (a wasted wake-up); a quicker answer lowers it at once."""
    p = proto(backend)
    call = read_holding_registers(1, 0, 10)
    answer = regs(backend, 1, list(range(10)))
    assert p.turnaround(1) is None
    now = 100.0
    learned = 0.0
    first = 5  # the shortest answer, then (the answer seen) the whole answer but a byte
    for late, after in ((0.002, 0.002), (0.002, 0.002), (0.0005, 0.0005)):
        p.start(*call, now=now)
        _adu, end = send(p, now)
        assert p.ready_at(end) == pytest.approx(end + T35 + learned + first * CHAR)
        first = len(answer) - 1
        arrive = end + T35 + late  # the first byte starts here
        p.receive_data(answer[:5], arrive + 5 * CHAR)  # read once 5 bytes are in
        learned = p.turnaround(1)  # type: ignore[assignment]
        assert learned == pytest.approx(after, abs=1e-9)
        p.receive_data(answer[5:], arrive + len(answer) * CHAR)
        assert p.result() == list(range(10))
        now = arrive + len(answer) * CHAR
    assert p.turnaround(1) == pytest.approx(0.0005)  # the quicker answer lowered it
    assert p.turnaround(2) is None  # per slave
    # a slower answer raises it only slowly (1/16 of the difference)
    p.start(*call, now=now)
    _adu, end = send(p, now)
    p.receive_data(answer[:5], end + T35 + 0.0105 + 5 * CHAR)
    assert p.turnaround(1) == pytest.approx(0.0005 + 0.01 / 16)
    # an echo or a line without timing learns nothing
    q = proto(backend, LineConfig(baudrate=9600, parity="N", t35=0))
    q.start(*call, now=1.0)
    _adu, end = send(q, 1.0)
    q.receive_data(answer[:5], end + 0.003)
    assert q.turnaround(1) is None and q.ready_at(end + 0.003) == end + 0.003


def test_a_repeated_request_is_read_in_one_wake_up(backend: ModuleType) -> None:
    """Once an answer to a request was seen, the first sleep of the next answer to
    the same request ends a character before that answer's end (one wake-up for the
    whole answer, the last byte read as it comes), not after its 5-byte header; an
    exception answer, shorter, is still taken; another request, or another line,
    starts from the header again; `needed` stays the framer's lower bound.  At any
    baud rate (38400 here; the wake-ups settle on the answer's end, see
    test_a_late_one_wake_up_moves_the_next_one_earlier)."""
    fast = LineConfig(baudrate=38400, parity="N")
    q = proto(backend, fast)
    answer = regs(backend, 1, list(range(10)))
    for now, first in ((1.0, 5), (2.0, len(answer) - 1)):
        q.start(*read_holding_registers(1, 0, 10), now=now)
        end = now + 8 * fast.char_time
        q.transmitted(end, now)
        assert q.ready_at(end) == pytest.approx(end + fast.t35_time + first * fast.char_time)
        q.receive_data(answer, end + fast.t35_time + 25 * fast.char_time)
        assert q.result() == list(range(10))
    line = LineConfig(baudrate=19200, parity="N")
    char, t35 = line.char_time, line.t35_time
    p = proto(backend, line)
    call = read_holding_registers(1, 0, 10)
    answer = regs(backend, 1, list(range(10)))

    def transact(c: tuple[Any, ...], reply: bytes, now: float) -> tuple[float, float]:
        p.start(*c, now=now)
        adu = p.data_to_send()
        end = now + len(adu) * char
        p.transmitted(end, now)
        first_sleep = p.ready_at(end)
        assert p.needed() == 5  # before any byte: the shortest answer (an exception)
        arrive = end + t35
        p.receive_data(reply, arrive + len(reply) * char)
        assert p.state is ClientState.DONE
        return end, first_sleep

    end, first = transact(call, answer, 10.0)
    assert first == pytest.approx(end + t35 + 5 * char)
    end, first = transact(call, answer, 11.0)
    assert first == pytest.approx(end + t35 + (len(answer) - 1) * char)
    # read a character early: the last byte is then waited for as input
    p.start(*call, now=12.0)
    adu = p.data_to_send()
    end = 12.0 + len(adu) * char
    p.transmitted(end, 12.0)
    wake = p.ready_at(end)
    p.receive_data(answer[:-1], wake)
    assert p.needed() == 1 and p.ready_at(wake) == wake
    p.receive_data(answer[-1:], wake + char)
    assert p.result() == list(range(10))
    # an exception answer to the same request: the error, read at the later wake-up
    exc = bytes(backend.add_crc(bytes((1, 0x83, 2))))
    p.start(*call, now=13.0)
    adu = p.data_to_send()
    end = 13.0 + len(adu) * char
    p.transmitted(end, 13.0)
    assert p.ready_at(end) == pytest.approx(end + t35 + (len(answer) - 1) * char)
    p.receive_data(exc, end + t35 + (len(answer) - 1) * char)
    with pytest.raises(ExceptionResponseError):
        p.result()
    # the normal answer's length is kept (an exception does not replace it)
    end, first = transact(call, answer, 14.0)
    assert first == pytest.approx(end + t35 + (len(answer) - 1) * char)
    # another request: from its header again
    other = read_holding_registers(1, 0, 3)
    end, first = transact(other, regs(backend, 1, [7, 8, 9]), 15.0)
    assert first == pytest.approx(end + t35 + 5 * char)
    # a new line (new rules) forgets the lengths
    p.set_line(line)
    end, first = transact(call, answer, 16.0)
    assert first == pytest.approx(end + t35 + 5 * char)


def test_ready_at_leaves_the_last_byte_to_a_wait_for_input(backend: ModuleType) -> None:
    """Once bytes of the answer are in, the sleep stops a character short and the last
    byte is read as it comes (a wait for input): a sleep would end up to a character
    after it, and the next request's t3.5 counts from that read."""
    answer = regs(backend, 1, list(range(10)))
    for baud, early in ((9600, 1), (19200, 1), (115200, 1)):
        line = LineConfig(baudrate=baud, parity="N")
        p = proto(backend, line)
        p.start(*read_holding_registers(1, 0, 10), now=5.0)
        adu = p.data_to_send()
        end = 5.0 + len(adu) * line.char_time
        p.transmitted(end, 5.0)
        t = end + line.t35_time + 5 * line.char_time
        p.receive_data(answer[:5], t)
        assert p.needed() == 20
        assert p.ready_at(t) == pytest.approx(t + (20 - early) * line.char_time)
        t += 24 * line.char_time - 5 * line.char_time
        p.receive_data(answer[5:24], t)
        assert p.needed() == 1
        assert p.ready_at(t) == pytest.approx(t + (1 - early) * line.char_time)


def test_a_late_one_wake_up_moves_the_next_one_earlier(backend: ModuleType) -> None:
    """A `ready_at` wake-up that finds the whole answer in was late by an unknown
    time: the learned turnaround drops a quarter character each time (never below
    0), so that the wake-ups settle on the answer's end; an early one (bytes still
    coming) learns the turnaround from them again."""
    line = LineConfig(baudrate=115200, parity="N")
    char, t35 = line.char_time, line.t35_time
    p = proto(backend, line)
    answer = regs(backend, 1, list(range(10)))
    t = 1.0

    def start() -> float:
        nonlocal t
        t += 1.0
        p.start(*read_holding_registers(1, 0, 10), now=t)
        p.transmitted(t + 8 * char, t)
        return t + 8 * char

    end = start()  # the first answer: the header, then the rest (turnaround 4 chars)
    p.receive_data(answer[:5], end + t35 + 9 * char)
    assert p.turnaround(1) == pytest.approx(4 * char)
    p.receive_data(answer[5:], end + t35 + 29 * char)
    assert p.result() == list(range(10))
    for k in (1, 2):  # late wake-ups: the whole answer in one read
        end = start()
        assert p.ready_at(end) == pytest.approx(
            end + t35 + (4 - (k - 1) / 4) * char + (len(answer) - 1) * char
        )
        p.receive_data(answer, end + t35 + 40 * char)
        assert p.result() == list(range(10))
        assert p.turnaround(1) == pytest.approx((4 - k / 4) * char)
    end = start()  # an early one: bytes still coming, the turnaround learned again
    p.receive_data(answer[:20], end + t35 + 23 * char)
    assert p.turnaround(1) == pytest.approx(3 * char)
    p.receive_data(answer[20:], end + t35 + 28 * char)
    assert p.result() == list(range(10))


def test_a_whole_answer_in_one_read_lowers_the_turnaround_a_little_on_a_slow_line(
    backend: ModuleType,
) -> None:
    """Up to 19200 baud a `Wait` comes a character before the answer's end and the
    last byte is waited for as input, while an `Xfer` reads at the predicted end:
    a whole answer read at once lowers the learned turnaround by `WAKE_STEP` (25 µs),
    not a quarter character, so that one slow answer does not keep every later read
    late."""
    line = LineConfig(baudrate=9600, parity="N")
    char, t35 = line.char_time, line.t35_time
    p = proto(backend, line)
    answer = regs(backend, 1, list(range(10)))
    for t in (2.0, 3.0):
        p.start(*read_holding_registers(1, 0, 10), now=t)
        end = t + 8 * char
        p.transmitted(end, t)
        if t == 2.0:
            p.receive_data(answer[:5], end + t35 + 7 * char)
        p.receive_data(answer if t == 3.0 else answer[5:], end + t35 + 40 * char)
        assert p.result() == list(range(10))
        lowered = WAKE_STEP if t == 3.0 else 0.0
        assert p.turnaround(1) == pytest.approx(2 * char - lowered)
