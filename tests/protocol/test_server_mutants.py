"""The server protocol's decisions that the mutation run (docs/MUTATION.md) found
untested: a request of a function without a rule read late after a nap (timed by
its CRC at the character rate), that function's last length as the nap's guess, a
nap for the last byte of a frame, no nap with a request all in, the echo's window.
Expected times from Serial Line V1.02 (a frame is one continuous stream, 2.5.1.1;
t3.5 before the answer), never read back from the protocol; on both backends."""

from __future__ import annotations

from types import ModuleType

import pytest
from test_server_protocol import BAUD, CHAR, LINE, T35, Harness, read_request

from pyrtu import pdu as pdus
from pyrtu.core.line import LineConfig
from pyrtu.protocol.server import Idle, Listen, Reply, ServerProtocol

#: a function with no length rule (user-defined, [MB] 5): framed by its CRC or the
#: silence after it; the slave answers it with exception 1
SHORT = b"\x01\x41\xaa\xbb"  # 6 bytes with the CRC
LONG = b"\x01\x41\xaa\xbb\xcc\xdd"  # 8


def _answered(h: Harness) -> float:
    """The silence after the request runs: when its answer is due."""
    deadline = h.proto.deadline()
    assert deadline is not None
    h.proto.handle_timer(deadline)
    pending = h.proto.pending
    assert pending is not None and pending.exception == 1
    return pending.earliest


def test_a_late_read_of_a_request_without_a_rule_is_timed_by_its_crc(
    backend: ModuleType,
) -> None:
    """After an 8-byte request the nap from the address alone is sized for 8 bytes; a
    6-byte request of a function with no rule comes instead: its end is where its
    CRC checks, at the character rate from the nap's start."""
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    adu = h.adu(SHORT)
    t0 = h.now
    h.proto.receive_data(adu[:1], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 7 * CHAR + T35)
    h.proto.receive_data(adu[1:], at)
    assert _answered(h) == pytest.approx(t0 + 5 * CHAR + T35, abs=2e-6)


def test_a_function_without_a_rule_naps_for_its_last_length(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(LONG))
    h.run_until_sent()
    h.now += 5 * T35
    adu = h.adu(LONG)
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 6 * CHAR + T35)


def test_a_shorter_request_than_its_functions_last_is_timed_by_its_crc(
    backend: ModuleType,
) -> None:
    h = Harness(backend)
    h.feed(h.adu(LONG))
    h.run_until_sent()
    h.now += 5 * T35
    adu = h.adu(SHORT)
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 6 * CHAR + T35)  # the last length: 8
    h.proto.receive_data(adu[2:], at)
    assert _answered(h) == pytest.approx(t0 + 4 * CHAR + T35, abs=2e-6)


def test_another_function_without_a_rule_has_no_length_guess(backend: ModuleType) -> None:
    h = Harness(backend)
    h.feed(h.adu(LONG))
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(h.adu(b"\x01\x42\xaa\xbb")[:2], t0)
    at = h.proto.wake_at(t0)
    # not 0x41's 8 bytes: at most the least rest of a frame (address, function, CRC)
    assert at is None or at <= t0 + 2 * CHAR + 1e-9


def test_a_frame_one_byte_short_naps_one_character(backend: ModuleType) -> None:
    h = Harness(backend)
    other = h.adu(read_request(unit=2))
    t0 = h.now
    h.proto.receive_data(other[:7], t0)
    assert h.proto.needed() == 1
    action = h.proto.next_action(t0)
    assert action == Listen(pytest.approx(t0 + CHAR), 1)


def test_no_nap_once_a_request_without_a_rule_is_all_in(backend: ModuleType) -> None:
    """Its last length is all in: nothing to sleep through (the silence ends it)."""
    h = Harness(backend)
    h.feed(h.adu(LONG))
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(h.adu(LONG), t0)
    assert h.proto.wake_at(t0) is None


def _echoed(h: Harness) -> tuple[bytes, float]:
    h.feed(h.adu(read_request()))
    out = h.proto.data_to_send(h.proto.deadline() or h.now)
    assert out is not None
    end = h.now + 0.05
    h.proto.transmitted(end)
    return out, end


def test_an_echo_within_twice_its_wire_time_and_200_ms_is_dropped(backend: ModuleType) -> None:
    h = Harness(backend, echo=True)
    out, end = _echoed(h)
    h.proto.receive_data(out, end + 2 * len(out) * CHAR + 0.2 - 1e-6)
    h.proto.handle_timer(end + 1.0)
    assert h.proto.counters["echo_dropped"] == 1


def test_an_echo_later_than_its_window_is_a_frame_seen(backend: ModuleType) -> None:
    h = Harness(backend, echo=True)
    out, end = _echoed(h)
    h.proto.receive_data(out, end + 2 * len(out) * CHAR + 0.2 + 0.001)
    h.proto.handle_timer(end + 1.0)
    assert h.proto.counters["echo_dropped"] == 0
    assert h.app.line.counters["bus_message_count"] == 2


def test_no_nap_in_ascii_even_where_the_address_is_the_colons_code(backend: ModuleType) -> None:
    """ASCII frames end at their delimiter, not at a length: no nap, even for slave 58
    (0x3A, ':'), whose frames begin with bytes that read as its own address."""
    line = LineConfig(baudrate=BAUD, parity="N", mode="ascii")
    h = Harness(backend, line, address=58)
    request = h.adu(read_request(unit=58))
    h.feed(request)
    assert h.run_until_sent()[0] is not None
    h.now += 1.0
    h.proto.receive_data(request[:5], h.now)
    assert h.proto.wake_at(h.now) is None


def test_a_late_read_with_bytes_after_the_request_is_timed_by_its_length(
    backend: ModuleType,
) -> None:
    """The nap's read brings the request's rest and the start of the next frame: the
    request (FC 03, 8 bytes by its rule) ended at the character rate from the nap's
    start, and is answered t3.5 after that."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 6 * CHAR + T35)
    h.proto.receive_data(adu[2:] + b"\x02\x03", at)
    pending = h.proto.pending
    assert pending is not None and pending.earliest == pytest.approx(t0 + 6 * CHAR + T35)


def test_one_nap_per_new_bytes(backend: ModuleType) -> None:
    """A nap is offered after new bytes only: asked again with none, the driver
    watches the port (or waits for a deadline)."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    first = h.proto.next_action(t0)
    assert type(first).__name__ == "Listen" and first.needed > 0  # type: ignore[attr-defined]
    h.proto.receive_data(b"", t0 + CHAR)  # the nap ended with nothing read
    again = h.proto.next_action(t0 + CHAR)
    assert getattr(again, "needed", 0) == 0


def test_a_request_after_a_late_read_is_timed_by_its_own_end(backend: ModuleType) -> None:
    """The late read's time stands for the frames all in it only: the next request,
    read as it comes, is answered t3.5 after its own last byte."""
    h = Harness(backend)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    at = h.proto.wake_at(t0)
    assert at is not None
    h.proto.receive_data(adu[2:], at + 0.0004)
    out, _ = h.run_until_sent()
    assert out is not None
    h.now += 5 * T35
    end = h.feed(adu)
    pending = h.proto.pending
    assert pending is not None and pending.earliest == pytest.approx(end + T35)


def test_a_driver_that_writes_ahead_listens_until_then(backend: ModuleType) -> None:
    """next_action(ahead=...): the response is handed out that long before its time,
    so the Listen before it ends that long before it."""
    h = Harness(backend)
    end = h.feed(h.adu(read_request()))
    action = h.proto.next_action(end, nap=False, ahead=0.001)
    assert action == Listen(pytest.approx(end + T35 - 0.001), 0)
    assert isinstance(action, Listen)
    reply = h.proto.next_action(action.until, nap=False, ahead=0.001)
    assert isinstance(reply, Reply) and reply.at == pytest.approx(end + T35)


def test_the_debug_log_names_the_request_and_the_answer(
    backend: ModuleType, caplog: pytest.LogCaptureFixture
) -> None:
    import logging

    caplog.set_level(logging.DEBUG, logger="pyrtu.drivers.slave")
    h = Harness(backend)
    request = h.adu(read_request(count=1))
    h.feed(request)
    out, _ = h.run_until_sent()
    assert out is not None
    messages = [r.getMessage() for r in caplog.records if r.name == "pyrtu.drivers.slave"]
    assert f"RX unit 1: {request.hex(' ')}" in messages
    assert f"TX unit 1: {out.hex(' ')}" in messages


def test_a_late_read_of_a_frame_short_of_its_rules_length_is_timed_by_the_read(
    backend: ModuleType,
) -> None:
    """The nap after "01 03" is sized for the 8-byte read request; the read brings 4
    bytes whose CRC checks on the 6 so far (a request cut short, not the 8 bytes of
    its rule).  No request of this slave ends in them by its length, so nothing says
    they came at the character rate: they are timed by the read, and the silence
    that ends the frame counts from there (t3.5 after the read, [SL] 2.5.1.1)."""
    h = Harness(backend)
    short = h.adu(b"\x01\x03\x00\x00")  # 6 bytes, its CRC right
    t0 = h.now
    h.proto.receive_data(short[:2], t0)
    at = h.proto.wake_at(t0)
    assert at is not None
    h.proto.receive_data(short[2:], at)
    assert h.proto.deadline() == pytest.approx(at + T35)
    out, _ = h.run_until_sent()
    assert out == h.adu(b"\x01\x83\x03")  # served: ILLEGAL DATA VALUE ([AP] 7)


def test_a_new_request_in_a_late_read_after_a_head_too_short_to_predict(
    backend: ModuleType,
) -> None:
    """ "01 17" (Read/Write Multiple registers, its length not known before byte 11)
    is left by a master that gave up; the nap's read, late, brings a whole new
    request, Read Exception Status (FC 07, 4 bytes).  No request ends in the read
    by its length, so it is timed by the read: a t3.5 silence before it, where a new
    frame may begin ([SL] 2.5.1.1), and FC 07 is answered t3.5 after the read, not
    after the lenient framer gives up on the first head."""
    h = Harness(backend)
    t0 = h.now
    h.proto.receive_data(b"\x01\x17", t0)
    at = h.proto.wake_at(t0)
    assert at is not None
    read = at + 5 * T35  # the driver read late
    h.proto.receive_data(h.adu(b"\x01\x07"), read)
    pending = h.proto.pending
    assert pending is not None and pending.adu[:2] == b"\x01\x07"
    assert pending.earliest == pytest.approx(read + T35)


def test_next_actions_options_are_keyword_only(backend: ModuleType) -> None:
    """``lead``, ``nap`` and ``ahead`` are keyword-only (the signature's ``*``): a
    driver passing them by position is refused, not read as another option."""
    h = Harness(backend)
    with pytest.raises(TypeError):
        h.proto.next_action(h.now, 0.0)  # type: ignore[call-arg]
    assert h.proto.next_action(h.now, lead=0.0, nap=True, ahead=0.0) == Idle()


def test_the_guess_from_the_address_alone_is_at_most_8_bytes(backend: ModuleType) -> None:
    """After a 9-byte request (a function with no rule, 5 data bytes), a new frame's
    address alone naps for 8 bytes at most, the longest FC 01..06 request ([AP]
    6.1-6.6: address, function, 4 bytes, CRC), not for the last request's 9."""
    h = Harness(backend)
    h.feed(h.adu(b"\x01\x41\xaa\xbb\xcc\xdd\xee"))  # 9 bytes with the CRC
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(b"\x01", t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + (8 - 1) * CHAR + T35)


def test_a_new_request_read_a_flush_timeout_after_an_abandoned_head(
    backend: ModuleType,
) -> None:
    """ "01 03" (an 8-byte read by its rule) is left by a master that gave up; the
    nap's read comes late, after more than the flush timeout, and brings a whole new
    read request.  Counted from the old head, the rule's 8 bytes do not end in a
    checking CRC: no request ends in the read by its length, so all of it is timed by
    the read.  The silence before it drops the old head (lenient mode, `flush_timeout`)
    and the new request is answered t3.5 after the read ([SL] 2.5.1.1)."""
    flush = 0.02
    line = LineConfig(baudrate=BAUD, parity="N", flush_timeout=flush)
    h = Harness(backend, line)
    t0 = h.now
    h.proto.receive_data(b"\x01\x03", t0)
    assert h.proto.wake_at(t0) is not None
    read = t0 + 2 * flush  # the driver read late
    h.proto.receive_data(h.adu(read_request(count=2)), read)
    pending = h.proto.pending
    assert pending is not None
    assert pending.adu == h.adu(b"\x01" + pdus.registers_response(3, [1000, 1001]))
    assert pending.earliest == pytest.approx(read + T35)


def test_the_watchdog_trips_at_exactly_its_time_in_next_action(backend: ModuleType) -> None:
    """The watchdog's time is a deadline like any other: asked at exactly that time,
    next_action lets it act (the time up to ``now`` acts, ``now`` included)."""
    tripped: list[object] = []
    watchdog = 0.5
    h = Harness(backend, watchdog=watchdog)
    h.app.on_watchdog = tripped.append
    end = h.feed(h.adu(read_request()))  # a valid request: framed at its last byte
    h.run_until_sent()
    h.proto.next_action(end + watchdog)
    assert tripped == [h.app] and h.proto.counters["watchdog_trips"] == 1


def test_a_request_framed_by_its_silence_is_answered_at_exactly_that_time(
    backend: ModuleType,
) -> None:
    """A function with no rule is framed by the t3.5 silence after it, when its answer
    is due as well ([SL] 2.5.1.1): next_action at exactly that time hands it out."""
    h = Harness(backend)
    end = h.feed(h.adu(SHORT))
    due = h.proto.deadline()
    assert due is not None and due == pytest.approx(end + T35, abs=2e-6)
    action = h.proto.next_action(due)
    assert action == Reply(h.adu(b"\x01\xc1\x01"), pytest.approx(end + T35, abs=2e-6))


def test_a_late_read_too_short_to_end_a_request_is_timed_by_the_read(
    backend: ModuleType,
) -> None:
    """The nap after "01" brings only "03" (fewer than the 4 bytes of the shortest
    ADU, [SL] 2.5.1.1: no request ends in it), so it is timed by the read, not by the
    character rate from the nap's start.  The rest of the request comes less than the
    flush timeout after that read, but more than it after the nap's start: the frame
    holds (lenient mode drops a frame only after a silence of the flush timeout) and
    is answered t3.5 after its last byte."""
    flush = 0.02
    line = LineConfig(baudrate=BAUD, parity="N", flush_timeout=flush)
    h = Harness(backend, line)
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:1], t0)
    assert h.proto.wake_at(t0) is not None
    read = t0 + 0.75 * flush  # the driver read late
    h.proto.receive_data(adu[1:2], read)
    end = read + 0.75 * flush  # 1.5 flush timeouts after the nap's start
    # (its 6 bytes at the character rate: the first began 6 characters before the end)
    assert end - 6 * CHAR - read < flush <= end - 6 * CHAR - (t0 + CHAR)
    h.now = end
    h.proto.receive_data(adu[2:], end)
    out, at = h.run_until_sent()
    assert out is not None and out[:2] == b"\x01\x03"
    assert at == pytest.approx(end + T35)


@pytest.mark.parametrize(("margin", "count"), [(-20e-6, 1), (20e-6, 2)])
def test_damaged_messages_count_apart_from_a_t35_silence_between_them(
    backend: ModuleType, margin: float, count: int
) -> None:
    """Two damaged messages ("55 aa 13": no function, no CRC) count as two
    communication errors (FC 08 sub-function 0x0C) when a t3.5 silence separates
    them ([SL] 2.5.1.1: frames are told apart by it), and as the pieces of one
    just under it.  8E1: 11 bits a character, t3.5 = 3.5 characters at 9600 baud."""
    char = 11 / 9600
    t35 = 3.5 * char
    h = Harness(backend, LineConfig(baudrate=9600, parity="E"))
    h.feed(b"\x55\xaa\x13", char)
    h.now += t35 + margin + char  # the next message's first byte ends a character on
    h.proto.receive_data(b"\x55", h.now)
    h.feed(b"\xaa\x13", char)
    h.now += 10 * t35
    h.proto.handle_timer(h.now)
    h.now = h.proto.deadline() or h.now
    h.proto.handle_timer(h.now)
    assert h.proto.deadline() is None  # both messages are over
    assert h.app.line.counters["bus_communication_error_count"] == count


def test_a_broadcasts_address_alone_naps_for_the_last_length_with_no_turnaround(
    backend: ModuleType,
) -> None:
    """A broadcast (address 0, [SL] 2.1) is a request to this slave too: from its
    address alone the nap is sized for the last request's 8 bytes, with no
    turnaround after it (a broadcast is never answered)."""
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(b"\x00", t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + (8 - 1) * CHAR)


def _long_write_head() -> bytes:
    """The first 7 bytes of Write Multiple Registers of 100 registers ([AP] 6.12):
    209 bytes on the wire, about 218 ms at 9600 baud."""
    return b"\x01\x10\x00\x00\x00\x64\xc8"


def test_a_nap_lasts_at_most_25_ms_half_the_default_flush_timeout(backend: ModuleType) -> None:
    """docs/MASTER_SLAVE.md: "a nap lasts at most half the framer's flush timeout",
    25 ms by default, exactly."""
    h = Harness(backend)
    t0 = h.now
    h.proto.receive_data(_long_write_head(), t0)
    action = h.proto.next_action(t0)
    assert isinstance(action, Listen)
    assert action.until == pytest.approx(t0 + 0.025, abs=1e-9)
    assert action.needed == int(0.025 / CHAR)  # the bytes that come in it


def test_a_nap_lasts_at_most_half_the_flush_timeout_given(backend: ModuleType) -> None:
    h = Harness(backend, LineConfig(baudrate=BAUD, parity="N", flush_timeout=0.02))
    t0 = h.now
    h.proto.receive_data(_long_write_head(), t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 0.01, abs=1e-9)


def test_a_request_all_in_a_late_read_after_another_is_timed_by_the_read(
    backend: ModuleType,
) -> None:
    """The nap's read brings the rest of a read request and a whole Read Exception
    Status (FC 07, 4 bytes) after it.  The first is stamped at the character rate
    from the nap's start; the second came at some time in the nap, so it counts from
    the read: answered t3.5 after it, and it replaces the first's answer (the master
    moved on)."""
    h = Harness(backend)
    first = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(first[:2], t0)
    at = h.proto.wake_at(t0)
    assert at is not None
    read = at + 0.002
    h.proto.receive_data(first[2:] + h.adu(b"\x01\x07"), read)
    pending = h.proto.pending
    assert pending is not None and pending.adu[:2] == b"\x01\x07"
    assert pending.earliest == pytest.approx(read + T35)
    assert h.app.line.counters["slave_no_response_count"] == 1


def test_writing_ahead_with_no_response_waiting_listens_until_the_framers_time(
    backend: ModuleType,
) -> None:
    """``ahead`` moves only a response's time: with none waiting, a driver that
    writes ahead listens until the framer's deadline (the t3.5 silence that ends a
    request with no rule)."""
    h = Harness(backend)
    end = h.feed(h.adu(SHORT))
    action = h.proto.next_action(end, nap=False, ahead=0.001)
    assert action == Listen(pytest.approx(end + T35, abs=2e-6), 0)


@pytest.mark.parametrize("ahead", [0.0, 0.001])
def test_a_framers_time_before_the_answers_is_kept(backend: ModuleType, ahead: float) -> None:
    """Noise after a request, while its answer waits for response_delay: the framer's
    t3.5 after the noise comes first, and the driver listens until then (writing
    ahead or not: ``ahead`` moves the answer's time only)."""
    h = Harness(backend, response_delay=0.05)
    end = h.feed(h.adu(read_request()))
    noise = end + 2 * CHAR
    h.proto.receive_data(b"\xff", noise)
    action = h.proto.next_action(noise, nap=False, ahead=ahead)
    assert action == Listen(pytest.approx(noise + T35, abs=2e-6), 0)


def test_another_slaves_address_naps_for_the_shortest_adu_after_served_frames(
    backend: ModuleType,
) -> None:
    """Address alone of a frame to another slave, after this slave served a request
    (bytes already framed): the nap is for the rest of the shortest ADU, function and
    CRC, 3 characters ([SL] 2.5.1.1: 4 bytes at least)."""
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(b"\x02", t0)
    assert h.proto.needed() == 3
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 3 * CHAR)


def test_a_rest_that_fits_the_longest_nap_exactly_is_napped_for_whole(
    backend: ModuleType,
) -> None:
    """A broadcast Write Multiple Coils of 104 coils ([AP] 6.11: 13 data bytes, 22
    bytes on the wire; not answered, so no turnaround) after its first 7 bytes: 15
    to come, and the longest nap (half the flush timeout) is exactly 15 characters:
    the nap is for all of them, not cut as a longer frame's nap is."""
    flush = 2 * 15 * CHAR
    h = Harness(backend, LineConfig(baudrate=BAUD, parity="N", flush_timeout=flush))
    t0 = h.now
    h.proto.receive_data(b"\x00\x0f\x00\x00\x00\x68\x0d", t0)
    action = h.proto.next_action(t0)
    assert action == Listen(pytest.approx(t0 + 15 * CHAR, abs=1e-9), 15)


def test_the_servers_options_are_keyword_only(backend: ModuleType) -> None:
    """``backend``, ``state``, ``echo``, ``response_delay`` and ``watchdog`` are
    keyword-only (the signature's ``*``): passed by position they are refused."""
    app = Harness(backend).app
    with pytest.raises(TypeError):
        ServerProtocol(LINE, app, backend)  # type: ignore[misc]
    assert ServerProtocol(LINE, app, backend=backend).backend is backend


def test_needed_is_0_in_ascii(backend: ModuleType) -> None:
    """ASCII frames end at their delimiter, not at a length: no lower bound on the
    bytes still to come, even with fewer than 4 in (":01")."""
    h = Harness(backend, LineConfig(baudrate=BAUD, parity="N", mode="ascii"))
    h.proto.receive_data(b":01", h.now)
    assert h.proto.needed() == 0


def test_a_new_request_in_a_late_read_after_a_head_without_a_rule(
    backend: ModuleType,
) -> None:
    """ "01 41" (no rule; its last request was 8 bytes long) is left by a master that
    gave up; the nap's read, late, brings a whole Read Exception Status (FC 07, 4
    bytes).  No CRC checks at any end of the old head, so no request ends in the read
    by it: the read is timed by the read, a t3.5 silence before it ([SL] 2.5.1.1),
    and FC 07 is answered t3.5 after the read."""
    h = Harness(backend)
    h.feed(h.adu(LONG))
    h.run_until_sent()
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(b"\x01\x41", t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 6 * CHAR + T35)
    read = at + 5 * T35  # the driver read late
    h.proto.receive_data(h.adu(b"\x01\x07"), read)
    pending = h.proto.pending
    assert pending is not None and pending.adu[:2] == b"\x01\x07"
    assert pending.earliest == pytest.approx(read + T35)


def _crc16(data: bytes) -> int:
    """CRC-16/MODBUS ([SL] 6.2.2), bit by bit: its low byte goes first on the wire."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def test_a_late_read_is_timed_by_a_whole_crc_not_by_its_high_byte(
    backend: ModuleType,
) -> None:
    """A 7-byte request of a function with no rule whose 4th byte is the high byte of
    the CRC of "01 41" (and its 3rd not the low one): "01 41 aa HH" is no frame, and
    the request's end is where its whole CRC checks, 7 bytes, at the character rate
    from the nap's start."""
    head = b"\x01\x41"
    high = _crc16(head) >> 8
    low = _crc16(head) & 0xFF
    message = head + bytes(((low + 1) & 0xFF, high, 0xCC))
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    adu = h.adu(message)
    assert len(adu) == 7 and _crc16(adu) == 0
    t0 = h.now
    h.proto.receive_data(adu[:1], t0)
    at = h.proto.wake_at(t0)
    assert at == pytest.approx(t0 + 7 * CHAR + T35)  # the last length: 8
    h.proto.receive_data(adu[1:], at)
    assert _answered(h) == pytest.approx(t0 + 6 * CHAR + T35, abs=2e-6)


def test_a_request_exactly_max_adu_long_naps_for_its_length(backend: ModuleType) -> None:
    """max_adu 8: a read request (8 bytes, [AP] 6.3) is exactly the longest ADU
    accepted, so it is napped for by its length and the turnaround."""
    h = Harness(backend, LineConfig(baudrate=BAUD, parity="N", max_adu=8))
    adu = h.adu(read_request())
    t0 = h.now
    h.proto.receive_data(adu[:2], t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + 6 * CHAR + T35)


def test_an_echo_at_exactly_the_end_of_its_window_is_dropped(backend: ModuleType) -> None:
    h = Harness(backend, echo=True)
    out, end = _echoed(h)
    h.proto.receive_data(out, end + 2 * len(out) * CHAR + 0.2)
    h.proto.handle_timer(end + 1.0)
    assert h.proto.counters["echo_dropped"] == 1


def test_a_stray_byte_dropped_before_a_request_is_not_its_address(backend: ModuleType) -> None:
    """A stray byte (0x05, another slave's address) after a served request, dropped
    by the silence after it; then a request's address alone: the nap is guessed from
    this slave's last request (8 bytes), the stray byte is no part of the frame."""
    h = Harness(backend)
    h.feed(h.adu(read_request()))
    h.run_until_sent()
    h.now += 5 * T35
    h.proto.receive_data(b"\x05", h.now)
    assert h.run_until_sent()[0] is None  # the silences after it drop it
    assert h.proto.deadline() is None
    h.now += 5 * T35
    t0 = h.now
    h.proto.receive_data(b"\x01", t0)
    assert h.proto.wake_at(t0) == pytest.approx(t0 + (8 - 1) * CHAR + T35)
