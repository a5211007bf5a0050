"""The sans-I/O server protocol (pyrtu.protocol.server) driven with synthetic time: no
ports, no sleeps.  Every path on both backends: normal, exception, broadcast,
ASCII, garbage, split requests, other addresses, turnaround, listen-only, echo,
watchdog, and the driver's `needed` hint."""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu import pdu as pdus
from pyrtu.core.ascii import encode_ascii
from pyrtu.core.line import LineConfig
from pyrtu.core.rules import LengthRule
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.protocol.datastore import DataStore
from pyrtu.protocol.server import ServerProtocol

BAUD = 9600
LINE = LineConfig(baudrate=BAUD, parity="N")
CHAR = LINE.char_time
T35 = LINE.t35_time


def make_store() -> DataStore:
    store = DataStore()
    store.holding_registers.add_range(0, [1000 + i for i in range(20)])
    return store


class Harness:
    """A SlaveBase (the functions, the DataStore) behind a protocol, fed byte-timed."""

    def __init__(
        self, backend: ModuleType, line: LineConfig = LINE, address: int = 1, **options: object
    ) -> None:
        self.backend = backend
        self.line = line
        self.store = make_store()
        self.app = SlaveBase(address, self.store, line=line, backend=backend.BACKEND)
        self.proto = ServerProtocol(line, self.app, backend=backend, state=self.app.line, **options)  # type: ignore[arg-type]
        self.now = 100.0

    def adu(self, message: bytes) -> bytes:
        if self.line.mode == "ascii":
            return encode_ascii(message)
        return bytes(self.backend.add_crc(message))

    def feed(self, data: bytes, spacing: float = CHAR) -> float:
        """``data`` one byte per ``spacing`` seconds; returns the time of the last byte."""
        for i in range(len(data)):
            self.now += spacing
            self.proto.receive_data(data[i : i + 1], self.now)
        return self.now

    def run_until_sent(self, limit: float = 5.0) -> tuple[bytes | None, float]:
        """Advance time deadline by deadline until a response is due (or ``limit``)."""
        end = self.now + limit
        while self.now < end:
            out = self.proto.data_to_send(self.now)
            if out is not None:
                self.proto.transmitted(self.now + len(out) * CHAR)
                return out, self.now
            deadline = self.proto.deadline()
            if deadline is None:
                return None, self.now
            self.now = max(self.now, deadline)
            self.proto.handle_timer(self.now)
        return None, self.now


def read_request(unit: int = 1, address: int = 0, count: int = 10) -> bytes:
    return bytes((unit,)) + pdus.read_request(pdus.READ_HOLDING_REGISTERS, address, count)


def test_normal_answer_after_t35(backend: ModuleType) -> None:
    h = Harness(backend)
    end = h.feed(h.adu(read_request()))
    assert h.proto.data_to_send(end) is None  # not before t3.5
    assert h.proto.data_to_send(end + T35 - 1e-6) is None
    assert h.proto.deadline() == pytest.approx(end + T35)
    out, at = h.run_until_sent()
    expected = h.adu(b"\x01" + pdus.registers_response(3, [1000 + i for i in range(10)]))
    assert out == expected
    assert at == pytest.approx(end + T35)
    assert h.proto.counters["responses"] == 1 and h.proto.counters["requests"] == 1
    assert h.proto.deadline() is None  # nothing left to do


def test_response_delay_adds_to_the_turnaround(backend: ModuleType) -> None:
    h = Harness(backend, response_delay=0.02)
    end = h.feed(h.adu(read_request()))
    out, at = h.run_until_sent()
    assert out is not None
    assert at == pytest.approx(end + T35 + 0.02)


def test_noise_after_the_request_does_not_move_the_answer(backend: ModuleType) -> None:
    h = Harness(backend)
    end = h.feed(h.adu(read_request()))
    h.now += 2 * CHAR
    h.proto.receive_data(b"\xff", h.now)
    out, at = h.run_until_sent()
    assert out is not None
    assert at == pytest.approx(end + T35)


def test_exception_response(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(read_request(address=15, count=10)))  # 15..24: past the range
    out, _ = h.run_until_sent()
    assert out == h.adu(b"\x01\x83\x02")
    assert h.proto.counters["exceptions"] == 1
    assert h.app.line.counters["slave_exception_error_count"] == 1


def test_unsupported_function_is_exception_1(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(b"\x01\x07"))
    h.app.functions.discard(7)
    h.feed(h.adu(b"\x01\x07"))
    out, _ = h.run_until_sent()
    assert out == h.adu(b"\x01\x87\x01")


def test_broadcast_write_is_executed_and_not_answered(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(b"\x00" + pdus.write_register_request(3, 0x1234)))
    out, _ = h.run_until_sent()
    assert out is None
    assert h.store.holding_registers.get(3) == 0x1234
    assert h.proto.counters["broadcasts"] == 1
    assert h.app.line.counters["slave_no_response_count"] == 1
    # a broadcast read is not executed either
    h.feed(h.adu(read_request(unit=0)))
    assert h.run_until_sent()[0] is None


def test_other_addresses_and_responses_are_ignored(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(read_request(unit=2)))
    assert h.run_until_sent()[0] is None
    assert h.proto.counters["ignored"] == 1
    # slave 2's answer on the shared bus is sized as a response, never taken for a request
    h.now += T35 * 2
    h.feed(h.adu(b"\x02" + pdus.registers_response(3, list(range(10)))))
    h.now += T35 * 2
    h.feed(h.adu(read_request()))
    out, _ = h.run_until_sent()
    assert out is not None and out[:2] == b"\x01\x03"
    assert h.app.line.counters["bus_message_count"] == 3


def test_address_change_is_seen_at_once(backend: ModuleType) -> None:
    h = Harness(backend)
    h.app.addresses = frozenset({9})
    h.feed(h.adu(read_request(unit=1)))
    assert h.run_until_sent()[0] is None
    h.feed(h.adu(read_request(unit=9)))
    out, _ = h.run_until_sent()
    assert out is not None and out[0] == 9


def test_garbage_before_the_request(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(b"\x55\xaa\x13")
    h.now += 2 * T35  # a silence: the garbage is a (damaged) message of its own
    h.proto.handle_timer(h.now)
    h.now = h.proto.deadline() or h.now
    h.proto.handle_timer(h.now)
    h.feed(h.adu(read_request()))
    out, _ = h.run_until_sent()
    assert out is not None and out[:3] == b"\x01\x03\x14"
    assert h.app.line.counters["bus_communication_error_count"] == 1


def test_bad_crc_is_silent(backend: ModuleType) -> None:
    h = Harness(backend)
    adu = bytearray(h.adu(read_request()))
    adu[-1] ^= 0xFF
    h.feed(bytes(adu))
    assert h.run_until_sent()[0] is None
    assert h.proto.counters["requests"] == 0


@pytest.mark.parametrize("cut", range(1, 8))
def test_request_split_at_every_byte_boundary(backend: ModuleType, cut: int) -> None:
    h = Harness(backend)
    adu = h.adu(read_request())
    h.now += CHAR
    h.proto.receive_data(adu[:cut], h.now)
    assert h.proto.data_to_send(h.now) is None
    h.now += (len(adu) - cut) * CHAR
    h.proto.receive_data(adu[cut:], h.now)
    end = h.now
    out, at = h.run_until_sent()
    assert out == h.adu(b"\x01" + pdus.registers_response(3, [1000 + i for i in range(10)]))
    assert at == pytest.approx(end + T35)


def test_needed_is_a_lower_bound_on_the_rest(backend: ModuleType) -> None:
    """A driver may sleep ``needed`` characters without missing the request's end:
    never more than the bytes still to come, never 0 while the request is incomplete
    (the slave role also sizes other slaves' responses, so it may be less)."""
    h = Harness(backend)
    adu = h.adu(read_request())
    assert h.proto.needed() == 0
    wakeups = 0
    got = 0
    while got < len(adu):
        step = max(1, h.proto.needed())
        assert step <= len(adu) - got
        h.feed(adu[got : got + step], spacing=0)
        h.now += step * CHAR
        got += step
        wakeups += 1
    assert h.proto.needed() == 0
    assert wakeups < len(adu)  # fewer wake-ups than bytes
    out, _ = h.run_until_sent()
    assert out is not None and out[:3] == b"\x01\x03\x14"


@pytest.mark.parametrize("cut", [1, 5, 16])
def test_ascii(backend: ModuleType, cut: int) -> None:
    line = LineConfig(baudrate=BAUD, parity="N", mode="ascii")
    h = Harness(backend, line)
    frame = encode_ascii(read_request(count=2))
    h.now += CHAR
    h.proto.receive_data(frame[:cut], h.now)
    h.now += CHAR
    h.proto.receive_data(frame[cut:], h.now)
    out = h.proto.data_to_send(h.now)  # ASCII: no t3.5 turnaround
    assert out == encode_ascii(b"\x01\x03\x04\x03\xe8\x03\xe9")


def test_listen_only_and_restart(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(b"\x01" + pdus.diagnostics_request(pdus.DIAG_FORCE_LISTEN_ONLY, 0)))
    assert h.run_until_sent()[0] is None
    assert h.app.listen_only
    h.feed(h.adu(read_request()))
    assert h.run_until_sent()[0] is None  # silent while listening
    assert h.store.holding_registers.get(0) == 1000
    h.feed(h.adu(b"\x01" + pdus.write_register_request(0, 7)))
    assert h.run_until_sent()[0] is None
    assert h.store.holding_registers.get(0) == 1000  # not executed either
    # restart communications: the one request served, not answered, leaves listen-only
    h.feed(h.adu(b"\x01" + pdus.diagnostics_request(pdus.DIAG_RESTART_COMMUNICATIONS, 0)))
    assert h.run_until_sent()[0] is None
    assert not h.app.listen_only
    h.feed(h.adu(read_request()))
    assert h.run_until_sent()[0] is not None


def test_echo_is_dropped_once(backend: ModuleType) -> None:
    h = Harness(backend, echo=True)
    h.feed(h.adu(read_request()))
    out, _ = h.run_until_sent()
    assert out is not None
    h.feed(out)  # the adapter's echo
    assert h.proto.counters["echo_dropped"] == 1
    assert h.run_until_sent()[0] is None
    assert h.app.line.counters["bus_message_count"] == 1


def test_new_request_replaces_a_pending_answer(backend: ModuleType) -> None:
    h = Harness(backend, response_delay=0.5)
    h.feed(h.adu(read_request(count=1)))
    h.now += T35
    h.feed(h.adu(read_request(address=1, count=1)))
    out, _ = h.run_until_sent()
    assert out == h.adu(b"\x01" + pdus.registers_response(3, [1001]))
    assert h.run_until_sent()[0] is None
    assert h.app.line.counters["slave_no_response_count"] == 1


def test_watchdog(backend: ModuleType) -> None:
    tripped: list[object] = []
    h = Harness(backend, watchdog=0.5)
    h.app.on_watchdog = tripped.append
    assert h.proto.deadline() is None  # armed by the first valid request
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    start = h.now
    deadline = h.proto.deadline()
    assert deadline is not None and deadline <= start + 0.5
    h.now = deadline
    h.proto.handle_timer(h.now)
    assert tripped == [h.app] and h.proto.counters["watchdog_trips"] == 1
    assert h.proto.deadline() is None  # once per silence
    h.feed(h.adu(read_request()))
    assert h.proto.deadline() is not None  # re-armed


def test_reconfigure_with_vendor_rules(backend: ModuleType) -> None:
    h = Harness(backend)
    """A vendor function whose request the framer cannot size without its rule."""
    h.app.protocol = h.proto
    h.app.register_function(0x41, lambda slave, unit, pdu: pdu[:2], LengthRule.fixed(7))
    h.feed(h.adu(b"\x01\x41\x01\x02\x03"))
    h.now += CHAR  # framed by the rule at once: no silence needed
    assert h.proto.data_to_send(h.now + T35) == h.adu(b"\x01\x41\x01")


def test_drop_response(backend: ModuleType) -> None:
    """A driver that stops forgets the answer still waiting (never sent later)."""
    h = Harness(backend, response_delay=0.5)
    h.feed(h.adu(read_request()))
    assert h.proto.pending is not None
    h.proto.drop_response()
    assert h.proto.pending is None
    assert h.run_until_sent()[0] is None
    assert h.app.line.counters["slave_no_response_count"] == 1


# ------------------------------------------------------------------ wake_at: naps


def test_wake_at_sleeps_through_the_request_and_its_turnaround(backend: ModuleType) -> None:
    """Address and function in: the request's length is known, so the driver may
    sleep to its end plus t3.5, read the rest late and answer at once; the answer's
    time comes from the character rate, not from the late read."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 6 * CHAR + T35)
    late = at + 0.0004  # the driver wakes late
    h.proto.receive_data(adu[2:], late)
    pending = h.proto.pending
    assert pending is not None and pending.earliest == pytest.approx(t0 + 6 * CHAR + T35)
    assert h.proto.data_to_send(late) == h.adu(
        b"\x01" + pdus.registers_response(3, [1000 + i for i in range(10)])
    )


def test_wake_at_guesses_the_last_length_from_the_address_alone(backend: ModuleType) -> None:
    h = Harness(backend)
    adu = h.adu(read_request())
    h.proto.receive_data(adu[:1], h.now)
    # nothing known yet: the least rest of any frame (4 bytes at least), no turnaround
    assert h.proto.wake_at(h.now) == pytest.approx(h.now + 3 * CHAR)
    h.proto.receive_data(adu[1:], h.now + 3 * CHAR)
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(adu[:1], t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 7 * CHAR + T35)


def test_a_wrong_guess_answers_late_never_early(backend: ModuleType) -> None:
    """After an 8-byte request the guess is 8; a 4-byte one (FC 07) ends sooner: it is
    answered at the guessed time (late), its t3.5 counted from its own end."""
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    short = h.adu(b"\x01\x07")
    t0 = h.now
    h.proto.receive_data(short[:1], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 7 * CHAR + T35)
    h.proto.receive_data(short[1:], at)
    pending = h.proto.pending
    assert pending is not None and pending.earliest == pytest.approx(t0 + 3 * CHAR + T35)
    assert h.proto.data_to_send(at) == h.adu(b"\x01\x07\x00")


def test_an_empty_read_ends_the_nap(backend: ModuleType) -> None:
    """The rest did not come when the nap ended (the master paused): bytes read later
    are not back-dated to the character rate."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    at = h.proto.wake_at(t0)
    assert at is not None
    h.proto.receive_data(b"", at)
    later = at + 2 * CHAR
    h.proto.receive_data(adu[2:], later)
    pending = h.proto.pending
    assert pending is not None and pending.earliest == pytest.approx(later + T35)


def test_wake_at_other_frames(backend: ModuleType) -> None:
    """Another slave's request or response, a broadcast: the least rest, no
    turnaround; ASCII, a pending answer, nothing in progress: watch the port."""
    h = Harness(backend)
    other = h.adu(read_request(unit=2))
    h.proto.receive_data(other[:2], h.now)
    at = h.proto.wake_at(h.now)
    assert at is not None and h.now < at <= h.now + 6 * CHAR
    h.proto.receive_data(other[2:], at)
    assert h.proto.wake_at(at) is None  # nothing in progress
    h.now = at + 2 * T35
    broadcast = h.adu(b"\x00" + pdus.write_register_request(3, 7))
    h.proto.receive_data(broadcast[:2], h.now)
    assert h.proto.wake_at(h.now) == pytest.approx(h.now + 6 * CHAR)
    h.proto.receive_data(broadcast[2:], h.now + 6 * CHAR)
    assert h.store.holding_registers.get(3) == 7
    h.now += 2 * T35
    h.feed(h.adu(read_request()))
    assert h.proto.pending is not None
    h.proto.receive_data(b"\x01", h.now)
    assert h.proto.wake_at(h.now) is None  # a response waits: the deadline rules
    line = LineConfig(baudrate=BAUD, parity="N", mode="ascii")
    a = Harness(backend, line)
    a.proto.receive_data(b":0103", a.now)
    assert a.proto.wake_at(a.now) is None


def _drive(h: Harness, adu: bytes, latency: float) -> tuple[float, float, int]:
    """A driver on a byte-timed line: byte i is in at t0 + (i + 1) CHAR; it wakes
    ``latency`` after the first byte, then at every ``wake_at`` plus ``latency``,
    reading all that is in.  Returns (the request's end, when the answer went out,
    wake-ups)."""
    t0 = h.now
    arrival = [t0 + (i + 1) * CHAR for i in range(len(adu))]
    now = arrival[0] + latency
    got = 0
    wakeups = 0
    while True:
        wakeups += 1
        ready = sum(1 for t in arrival if t <= now)
        h.proto.receive_data(adu[got:ready], now)
        got = ready
        out = h.proto.data_to_send(now)
        if out is not None:
            h.now = now
            h.proto.transmitted(now + len(out) * CHAR)
            return arrival[-1], now, wakeups
        at = h.proto.wake_at(now)
        if at is None:
            at = h.proto.deadline()
        if at is None:  # watching the port: the next byte
            at = arrival[got]
        now = max(at, now) + latency
        assert wakeups < 3 * len(adu)


@pytest.mark.parametrize("latency", [0.0, 0.3 * CHAR, 2.5 * CHAR])
@pytest.mark.parametrize(
    "message",
    [
        read_request(),
        b"\x01\x07",
        b"\x01" + pdus.write_registers_request(0, list(range(10))),
        b"\x01\x2b\x0e\x01\x00",
    ],
    ids=["fc03", "fc07", "fc16", "fc43"],
)
def test_driven_naps_never_answer_early(
    backend: ModuleType, message: bytes, latency: float
) -> None:
    """Whatever the guess and the driver's lateness, the answer goes out no sooner
    than t3.5 after the request's last byte, and on time plus the lateness when
    the guess holds; a repeated request takes two wake-ups, three when it is longer
    than the 8 bytes guessed from the address alone."""
    h = Harness(backend)
    adu = h.adu(message)
    for i, first in enumerate([read_request(), message, message]):
        request = h.adu(first)
        end, sent, wakeups = _drive(h, request, latency)
        assert sent >= end + T35 - 1e-9
        if i == 2:  # the same request again: the guess holds
            assert sent <= end + T35 + latency + CHAR + 1e-9
            assert wakeups == (2 if len(request) <= 8 else 3)
        h.now = sent + (len(adu) + 60) * CHAR + T35


def test_wake_at_with_a_lead_prepares_during_the_turnaround(backend: ModuleType) -> None:
    """``lead``: wake that much before the answer's time (at most half of t3.5, so the
    request is in), prepare it, and send it at its time, not sooner."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    assert h.proto.wake_at(t0, lead=0.0005) == pytest.approx(t0 + 6 * CHAR + T35 - 0.0005)
    at = h.proto.wake_at(t0, lead=1.0)  # capped
    assert at == pytest.approx(t0 + 6 * CHAR + T35 / 2)
    h.proto.receive_data(adu[2:], at)
    assert h.proto.data_to_send(at) is None  # prepared, not due
    assert h.proto.deadline() == pytest.approx(t0 + 6 * CHAR + T35)
    out, sent = h.run_until_sent()
    assert out is not None and sent == pytest.approx(t0 + 6 * CHAR + T35)
