"""The server protocol's one entry point for drivers (`ServerProtocol.next_action`),
its RTU and ASCII framer cores behind one feed/take interface, the one feed loop
(`pyrtu.core.feed.feed_all`) and the active backend's request predictor."""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu.core.ascii import AsciiCore, AsciiFramer, encode_ascii
from pyrtu.core.feed import feed_all
from pyrtu.core.frames import ErrorReason, FrameKind
from pyrtu.core.framing import PRED_LENGTH, PRED_NEED, PRED_UNKNOWN, FramerCore
from pyrtu.core.line import LineConfig
from pyrtu.protocol import Idle, Listen, Reply, ServerAction, ServerProtocol

BAUD = 19200


class App:
    """FC 03 of one register, 0x1234, at address 1."""

    addresses = frozenset({1})

    def __init__(self) -> None:
        self.requests: list[bytes] = []

    def execute(self, unit: int, request: bytes) -> bytes | None:
        self.requests.append(request)
        return bytes.fromhex("03 02 1234")

    def watchdog_expired(self) -> None:
        raise AssertionError("no watchdog here")


def _proto(backend: ModuleType, mode: str = "rtu") -> ServerProtocol:
    return ServerProtocol(LineConfig(baudrate=BAUD, parity="N", mode=mode), App(), backend=backend)


# ----------------------------------------------------------------- next_action


def test_rtu_transaction_through_next_action(backend: ModuleType) -> None:
    """First byte -> a nap sized for the rest of the request (its length: the last
    request's) plus t3.5; the rest read after it -> the answer, due t3.5 after the
    request's end on the line, in that same wake-up."""
    proto = _proto(backend)
    char, t35 = proto.char_time, proto.turnaround
    assert proto.next_action(0.0) == Idle()
    request = backend.add_crc(bytes.fromhex("01 03 0000 0001"))
    answer = backend.add_crc(bytes.fromhex("01 03 02 1234"))
    for start in (1.0, 2.0):  # the first request teaches the slave its length
        now = start
        proto.receive_data(request[:1], now)
        action = proto.next_action(now)
        while not isinstance(action, Reply):
            assert isinstance(action, Listen) and action.needed > 0
            got = proto._received % len(request)
            now = action.until
            proto.receive_data(request[got : got + action.needed] if got else b"", now)
            action = proto.next_action(now)
        assert action.data == answer
        assert action.at == pytest.approx(start + 7 * char + t35, abs=2e-6)
        proto.transmitted(now + len(answer) * char)
    # the second: one nap for the whole request, ending with its answer's time
    assert proto.counters["requests"] == proto.counters["responses"] == 2
    proto.receive_data(request[:1], 3.0)
    nap = proto.next_action(3.0)
    assert nap == Listen(pytest.approx(3.0 + 7 * char + t35), len(request) - 1)


def test_no_nap_for_a_driver_that_watches_the_port(backend: ModuleType) -> None:
    proto = _proto(backend)
    request = backend.add_crc(bytes.fromhex("01 03 0000 0001"))
    proto.receive_data(request[:3], 1.0)
    action = proto.next_action(1.0, nap=False)
    # the framer's silence timer (t1.5/t3.5 after the last byte), not a nap
    assert isinstance(action, Listen) and action.needed == 0
    proto.receive_data(request[3:], 1.0 + 5 * proto.char_time)
    wait = proto.next_action(1.0 + 5 * proto.char_time, nap=False)
    assert isinstance(wait, Listen) and wait.needed == 0  # the answer's time
    reply = proto.next_action(wait.until, nap=False)
    assert isinstance(reply, Reply) and reply.at == wait.until


def test_ascii_transaction_has_no_nap(backend: ModuleType) -> None:
    """ASCII frames end at CR LF, not at a length: the driver watches the port."""
    proto = _proto(backend, "ascii")
    request = encode_ascii(bytes.fromhex("01 03 0000 0001"))
    proto.receive_data(request[:5], 1.0)
    action = proto.next_action(1.0)
    assert isinstance(action, Listen) and action.needed == 0  # the 1 s character limit
    assert action.until == pytest.approx(2.0, abs=1e-5)
    proto.receive_data(request[5:], 1.01)
    reply = proto.next_action(1.01)
    assert isinstance(reply, Reply) and reply.data == encode_ascii(bytes.fromhex("01 03 02 1234"))
    assert proto.counters["responses"] == 1


def test_actions_are_one_event_type() -> None:
    for action in (Reply(b"\x01", 1.0), Listen(2.0, 3), Idle()):
        assert isinstance(action, ServerAction)


# ----------------------------------------------------------------- the cores


def test_rtu_and_ascii_framers_share_the_core_interface(backend: ModuleType) -> None:
    members = [m for m in dir(FramerCore) if not m.startswith("_")]
    for core in (backend.Framer("slave").core, AsciiFramer("slave").core):
        for name in members:
            assert callable(getattr(core, name)), (type(core).__name__, name)
    assert isinstance(_proto(backend, "ascii").framer.core, AsciiCore)


def test_ascii_core_events_as_on_the_wire() -> None:
    core = AsciiCore("slave", 1_000_000)
    frame = encode_ascii(bytes.fromhex("01 03 0000 0001"))
    garbage = b"noise" * 1000
    assert core.feed(garbage + frame, 5_000_000) == len(garbage) + len(frame)
    # the characters outside a frame: one discard event, not one per character
    offset, length, kind, error, _start, end, wire = core.poll() or ()
    assert (offset, length, kind, wire) == (0, len(garbage), FrameKind.DISCARD, garbage)
    assert error and end == 5_000_000
    offset, length, kind, error, _start, end, wire = core.poll() or ()
    assert (offset, length, kind, error, wire) == (len(garbage), len(frame), 0, 0, frame)
    assert core.poll() is None


def test_ascii_core_silence_discard_has_its_offset() -> None:
    framer = AsciiFramer("slave", inter_char=0.5)
    framer.receive_data(b"xx:0103", 1.0)
    framer.receive_data(b"00", 2.0)  # more than 0.5 s later: the frame is cut
    events = framer.events()
    assert [e.error for e in events] == [ErrorReason.TRUNCATED, ErrorReason.T15] * 1 + [
        ErrorReason.TRUNCATED
    ]
    assert [(e.offset, e.wire) for e in events] == [(0, b"xx"), (2, b":0103"), (7, b"00")]
    assert framer.counters == {"frames": 0, "discarded_bytes": 9, "lrc_errors": 0}


def test_ascii_timer_is_when_handle_timer_acts() -> None:
    framer = AsciiFramer("slave", inter_char=0.5)
    framer.receive_data(b":01", 1.0)
    timer = framer.timer()
    assert timer is not None
    framer.handle_timer(timer - 1e-6)
    assert framer.next_event() is None
    framer.handle_timer(timer)
    event = framer.next_event()
    assert event is not None and event.error is ErrorReason.T15


# ----------------------------------------------------------------- feed_all


class _Stuck:
    """A core that takes nothing: only a broken core does that (no real input can)."""

    def __init__(self) -> None:
        self.calls = 0

    def feed(self, data: bytes) -> int:
        self.calls += 1
        return 0


def test_feed_all_stops_on_a_core_that_makes_no_progress() -> None:
    stuck = _Stuck()
    with pytest.raises(RuntimeError, match="no progress"):
        feed_all(stuck.feed, b"\x01\x02", lambda: None)
    assert stuck.calls == 3


def test_feed_all_feeds_the_rest_after_each_frame(backend: ModuleType) -> None:
    """The RTU core stops at a frame's end; the loop takes its event and goes on."""
    core = backend.Framer("slave").core
    request = backend.add_crc(bytes.fromhex("01 03 0000 0001"))
    events: list[tuple[int, ...]] = []

    def drain() -> None:
        while (ev := core.poll()) is not None:
            events.append(ev[:4])

    assert feed_all(lambda chunk: core.feed(chunk, 1_000), request * 3, drain) == 24
    assert [e[:2] for e in events] == [(0, 8), (8, 8), (16, 8)]


def test_feed_all_stops_when_drain_says_so(backend: ModuleType) -> None:
    """A silence before the new bytes ends the frame in progress first: the core
    takes none of them; a drain that says stop leaves them untaken."""
    core = backend.Framer("slave").core
    request = backend.add_crc(bytes.fromhex("01 03 0000 0001"))
    assert core.feed(request[:4], 1_000) == 4
    late = 10_000_000
    assert feed_all(lambda chunk: core.feed(chunk, late), request[4:] + request, lambda: True) == 0
    core.reset()
    assert core.feed(request[:4], 1_000) == 4
    rest = request[4:] + request
    events: list[int] = []

    def drain() -> None:
        while (ev := core.poll()) is not None:
            events.append(ev[1])

    assert feed_all(lambda chunk: core.feed(chunk, late), rest, drain) == len(rest)
    assert events == [4]  # the request cut by the silence; the rest is buffered


# ----------------------------------------------------------------- the predictor


def test_the_protocol_predicts_with_its_own_backend(backend: ModuleType) -> None:
    """Under the C backend the C core's rtu_predict, not the twin's predictor."""
    predict = _proto(backend)._predict
    owner = getattr(predict, "__module__", None) or type(predict).__module__
    assert owner == backend.__name__


def test_backends_predict_request_lengths_alike(both: tuple[ModuleType, ModuleType]) -> None:
    options = LineConfig(baudrate=BAUD).options("slave")
    predictors = [b.request_predictor(options) for b in both]
    seen = set()
    for fc in range(256):
        for tail in (b"", b"\x00", b"\x0e\x01", b"\x00\x00\x00\x02\x04"):
            adu = bytes((1, fc)) + tail
            results = {p(adu) for p in predictors}
            assert len(results) == 1, (adu.hex(), results)
            seen.add(results.pop()[0])
    assert seen == {PRED_LENGTH, PRED_NEED, PRED_UNKNOWN}
