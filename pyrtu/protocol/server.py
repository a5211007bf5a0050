"""The Modbus serial server (slave) as a sans-I/O state machine, in h11's shape.

Bytes and times go in, response bytes and the earliest time they may go out come
out; nothing here reads a port, sleeps or looks at a clock.  A driver is a short
interpreter of the protocol's next action (see docs/PROTOCOL.md)::

    proto = ServerProtocol(line, app)        # line: a LineConfig
    while True:
        action = proto.next_action(now())
        if isinstance(action, Reply):        # write it now, then say when it ended
            start, end = port.write(action.data)
            proto.transmitted(end)
        elif isinstance(action, Listen) and action.needed:
            sleep_until(action.until)        # the rest of a frame: not watching the port
            proto.receive_data(port.read_available(), now())   # even b""
        else:                                # Listen: until action.until; Idle: no limit
            data = port.read(timeout=...)
            if data:
                proto.receive_data(data, now())

`receive_data`, `handle_timer`, `deadline`, `wake_at`, `data_to_send` and
`transmitted` are the steps `next_action` is made of, public for tests and drivers
with needs of their own.  RTU and ASCII differ only below the framer core's
feed/take interface (`pyrtu.core.framing.FramerCore`, `pyrtu.core.ascii.AsciiCore`) and in a
codec chosen once per line (`_Codec`).

The request frames the framer (slave role) cuts from the line are executed by the
*application* (`pyrtu.Slave`, `pyrtu.drivers.aio.AsyncSlave`: the DataStore, the standard
functions and the vendor handlers); the protocol keeps what belongs to the serial
line: addressing and broadcast (Serial Line V1.02, 2.1), listen-only mode and the
counters (`LineState`, FC 08/11/12), the echo of an echoing adapter, the watchdog,
and the turnaround.  A response goes out no sooner than t3.5 after the end of the
request (Serial Line V1.02, 2.5.1.1: frames are separated by a t3.5 silence), plus
``response_delay`` for devices whose manual gives one.  A new request before the
pending response went out replaces it (the master moved on; the first one counts
as not answered).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import NamedTuple, Protocol

from pyrtu.core import _backend
from pyrtu.core.ascii import (
    INTER_CHAR_LIMIT,
    ascii_message,
    delimiter_table,
    encode_ascii,
    make_framer,
)
from pyrtu.core.feed import feed_all
from pyrtu.core.frames import ERROR_BY_CODE
from pyrtu.core.framing import PRED_LENGTH, PRED_UNKNOWN, FramerCore
from pyrtu.core.line import LineConfig
from pyrtu.core.options import DEFAULT_FLUSH_US
from pyrtu.pdu.errors import SlaveException
from pyrtu.protocol.diagnostics import LineState

log = logging.getLogger("pyrtu.drivers.slave")

_MIN_ADU = 4
#: the longest request length guessed from the address alone: FC 01..06 requests
#: (Application Protocol V1.1b 6.1-6.6); the shortest (FC 07, 11, 12, 17) are 4 bytes
_GUESS_MAX = 8
_REQUEST = 0  # FrameKind.REQUEST, RTU_KIND_REQUEST

COUNTER_NAMES = (
    "requests",
    "responses",
    "exceptions",
    "broadcasts",
    "ignored",
    "echo_dropped",
    "watchdog_trips",
)


class Application(Protocol):
    """What a server asks of the slave behind it: the serial `ServerProtocol` and the
    TCP server (`pyrtu.tcp.server.TcpServer`) alike."""

    #: the addresses served (read for every frame: a device may change its own)
    addresses: frozenset[int]

    def execute(self, unit: int, request: bytes) -> bytes | None:
        """The response PDU of ``request`` for ``unit`` (0: broadcast), or None."""
        ...


class WatchedApplication(Application, Protocol):
    """An `Application` told when the serial line's watchdog expires (what the
    serial protocol asks of the slave behind it)."""

    def watchdog_expired(self) -> None:
        """No valid request for the watchdog time."""
        ...


@dataclass(slots=True)
class ServerAction:
    """What the driver of a `ServerProtocol` does next (`ServerProtocol.next_action`):
    one of `Reply`, `Listen`, `Idle`."""


@dataclass(slots=True)
class Reply(ServerAction):
    """Write ``data`` now (it became due at ``at``), then call
    `ServerProtocol.transmitted` with the time its last byte left the wire.  Handed
    out ahead (``next_action(now, ahead=...)``), ``at`` may be later than ``now``:
    then write it at ``at``."""

    data: bytes
    at: float


@dataclass(slots=True)
class Listen(ServerAction):
    """Wait for input until ``until`` at the latest, then ask again.

    ``needed`` 0: watch the port, give what comes to `receive_data` as it comes.
    ``needed`` n > 0: the rest of a frame, about n bytes, is due by ``until``; the
    driver may sleep until then without watching the port (one wake-up for the whole
    frame), then read what there is and give it to `receive_data`, even nothing."""

    until: float
    needed: int = 0


@dataclass(slots=True)
class Idle(ServerAction):
    """Nothing to do until bytes come: watch the port with no time limit."""


_IDLE = Idle()


class _Codec(NamedTuple):
    """What differs between RTU and ASCII above the framer core, chosen once per line."""

    encode: Callable[[bytes], bytes]  # address + PDU -> the frame on the wire
    message: Callable[[bytes], bytes]  # a frame the core checked -> address + PDU
    incoming: Callable[[bytes, LineState], bytes]  # bytes read -> bytes for the core
    by_length: bool  # frames end at a length the rules predict (naps: see wake_at)
    boundary: float  # the silence that tells damaged messages apart (LineState)


def _strip_crc(adu: bytes) -> bytes:
    return adu[:-2]


def _as_read(data: bytes, state: LineState) -> bytes:
    return data


def _ascii_delimiter(data: bytes, state: LineState) -> bytes:
    """ASCII: the frame end the master chose (FC 08 sub-function 0x03) as LF."""
    char = state.ascii_delimiter
    return data if char == 0x0A else data.translate(delimiter_table(char))


def _codec(line: LineConfig, backend: ModuleType) -> _Codec:
    if line.mode == "ascii":
        return _Codec(encode_ascii, ascii_message, _ascii_delimiter, False, INTER_CHAR_LIMIT)
    # damaged messages are told apart by the spec's t3.5 (whatever t35 says)
    spec = line.replace(t15=None, t35=None).t35_time
    return _Codec(backend.add_crc, _strip_crc, _as_read, True, spec)


class Response(NamedTuple):
    """A response waiting for its time: the ADU and the earliest time to send it."""

    unit: int
    adu: bytes
    earliest: float
    exception: int | None


class ServerProtocol:
    """One serial port of a slave: frames in, responses out, time as an input.

    ``line``: the line (mode, timing, rules); the protocol keeps a slave-role framer
    of it (``backend``: the RTU framer's implementation).  ``app`` executes the
    requests; ``state``: the serial-line counters and modes (FC 08/11/12);
    ``echo``: the adapter echoes what is sent; ``response_delay``: added to the
    turnaround (a device's manual); ``watchdog``: seconds without a valid request
    before ``app.watchdog_expired()``.
    """

    def __init__(
        self,
        line: LineConfig,
        app: WatchedApplication,
        *,
        backend: ModuleType | str | None = None,
        state: LineState | None = None,
        echo: bool = False,
        response_delay: float = 0.0,
        watchdog: float | None = None,
    ) -> None:
        self.app = app
        self.backend = _backend.backend(backend) if not isinstance(backend, ModuleType) else backend
        self.response_delay = response_delay
        self.watchdog = watchdog
        self.echo = echo
        self.state = LineState() if state is None else state
        self.counters = dict.fromkeys(COUNTER_NAMES, 0)
        self.reconfigure(line)
        self._pending: Response | None = None
        self._echo: bytes | None = None  # what was sent, expected back (echo=True)
        self._echo_until = 0.0
        self._sending: Response | None = None
        self._last_valid: float | None = None
        self._tripped = False

    def reconfigure(self, line: LineConfig) -> None:
        """Take ``line`` (new rules, say) from now on; bytes being framed are dropped."""
        self.line = line
        #: the slave-role framer of the line (RTU or ASCII); the protocol drives its core
        self.framer = make_framer(line, "slave", self.backend)
        self._core: FramerCore = self.framer.core
        self._codec = codec = _codec(line, self.backend)
        self._encode = codec.encode
        self._message = codec.message
        self._received = 0  # bytes given to the framer
        self._framed = 0  # of which the framer has ended (frames and discards)
        self._head = bytearray()  # the bytes of the frame in progress
        self._fresh = False  # bytes came since the last next_action
        #: napping (see `wake_at`): (since, bytes given by then, bytes it waits for)
        self._nap: tuple[float, int, int] | None = None
        #: the last bytes read after a nap: (from, to) in the stream, and when
        self._late: tuple[int, int, float] | None = None
        self._predict: Callable[[bytes], tuple[int, int]] = self.backend.request_predictor(
            line.options("slave")
        )
        self._last_length = 0  # of the last request to this slave (see wake_at)
        self._last_function = -1
        self.max_adu = line.max_adu
        #: the longest nap (see `wake_at`): half the silence after which a lenient
        #: framer drops an incomplete frame, so that no timing of the bytes read
        #: after a nap invents a silence that long
        flush = DEFAULT_FLUSH_US / 1e6 if line.flush_timeout is None else line.flush_timeout
        self._nap_limit = max(flush, line.t35_time) / 2
        #: the silence kept after a request (t3.5 in RTU; none in ASCII)
        self.turnaround = line.frame_gap
        self.char_time = line.char_time
        self.state.boundary = codec.boundary

    # ----------------------------------------------------------------- inputs

    def receive_data(self, data: bytes, now: float) -> None:
        """Bytes that arrived (were read) at ``now``.  After a nap (`wake_at`), give
        what the read returned, even nothing: that ends the nap."""
        nap, self._nap = self._nap, None
        if not data:
            return
        data = self._codec.incoming(data, self.state)
        self._fresh = True
        self._received += len(data)
        head = self._head
        head += data
        now_us = round(now * 1_000_000)
        if nap is not None:
            # read late after a nap, not watching the port.  The bytes that end the
            # frame in progress came at the character rate after the ones read
            # before it (a frame is one continuous stream, Serial Line V1.02
            # 2.5.1.1), and are timed so: those the nap was sized for, or else
            # those that end a request to this slave, its CRC checking.  Timed by
            # the late read, they would show the framer a silence that never was,
            # the nap's excess over the frame (a guess too long), and a lenient
            # framer drops a frame cut by a silence of flush_timeout.  The bytes
            # after them, and all when no request ends in them (noise that looked
            # like one, and what came after it), by the read; a nap never lasts more
            # than half the flush timeout (`_sleep`), so that no timing invents a
            # silence that long.  A frame all in these bytes may have come at any
            # time in the nap: its answer's time counts from the read (`_on_frame`).
            at, then, sized = nap
            count = len(data)
            ends = count if count == sized else self._request_end(count)
            if ends:
                stamp = at + (self._received - count + ends - then) * self.char_time
                self._late = (then, self._received, now)
                # (down to the microsecond: the answer is due when the nap ends)
                self._feed(data[:ends], min(int(stamp * 1_000_000), now_us), now)
                data = data[ends:]
        if data:
            self._feed(data, now_us, now)
        excess = len(head) - (self._received - self._framed)
        if excess > 0:
            del head[:excess]

    def _feed(self, data: bytes, now_us: int, now: float) -> None:
        """``data`` to the framer's core, arrived by ``now_us``; its frames out (a
        silence before the bytes, or a frame ended in them: the core takes fewer)."""
        core = self._core
        feed_all(lambda chunk: core.feed(chunk, now_us), data, lambda: self._core_events(now))

    def _request_end(self, count: int) -> int:
        """How many of the ``count`` bytes just added to the head end the request to
        this slave (or broadcast) begun before them, its CRC checking: its length
        from the rules, else (no rule) the first that checks; 0: none ends in them."""
        head = self._head
        n = len(head)
        before = n - count
        if before < 1 or n < _MIN_ADU or not (head[0] == 0 or head[0] in self.app.addresses):
            return 0
        status, length = self._predict(bytes(head))
        if status == PRED_LENGTH:
            ok = before < length <= n and self.backend.check_crc(head[:length])
            return length - before if ok else 0
        if status != PRED_UNKNOWN:
            return 0
        crc16 = self.backend.crc16
        crc = crc16(head[: _MIN_ADU - 2])
        for end in range(_MIN_ADU, n + 1):  # framed by its silence: where its CRC checks
            if end > before and head[end - 2] == crc & 0xFF and head[end - 1] == crc >> 8:
                return end - before
            crc = crc16(head[end - 2 : end - 1], crc)
        return 0

    def handle_timer(self, now: float) -> None:
        """Let the time up to ``now`` end what it ends (frames, the watchdog)."""
        core = self._core
        deadline = core.deadline()
        if deadline is not None and now >= deadline / 1e6:
            core.handle_timer(round(now * 1_000_000))
            self._core_events(now)
        if (
            self.watchdog is not None
            and self._last_valid is not None
            and not self._tripped
            and now - self._last_valid >= self.watchdog
        ):
            self._tripped = True
            self.counters["watchdog_trips"] += 1
            self.app.watchdog_expired()

    def transmitted(self, end: float) -> None:
        """The response handed out by `data_to_send` left the wire at ``end``."""
        sent, self._sending = self._sending, None
        if sent is not None and self.echo:
            # the echo comes back within its own wire time (and some adapter latency)
            self._echo = sent.adu
            self._echo_until = end + 2 * len(sent.adu) * self.char_time + 0.2

    def drop_response(self) -> None:
        """Forget the response waiting for its time (the driver stopped: when it serves
        again the master has long moved on); it counts as not answered."""
        self._nap = None
        if self._pending is not None:
            self._pending = None
            self.state.not_answered()

    # ---------------------------------------------------------------- outputs

    def deadline(self) -> float | None:
        """When `handle_timer` or `data_to_send` has work (None: only bytes will do)."""
        timer = self._core.deadline()
        at = None if timer is None else timer / 1e6
        if self._pending is not None and (at is None or self._pending.earliest < at):
            at = self._pending.earliest
        if self.watchdog is not None and self._last_valid is not None and not self._tripped:
            expiry = self._last_valid + self.watchdog
            if at is None or expiry < at:
                at = expiry
        return at

    def needed(self) -> int:
        """A lower bound on the bytes the frame being received still needs (0: unknown
        or none): the framer's, and where it predicts one, in RTU at least the rest of
        the shortest ADU (address, function, CRC: 4 bytes, Serial Line V1.02 2.5.1.1)."""
        needed = self._core.needed()
        started = self._received - self._framed
        if needed and 0 < started < _MIN_ADU:  # (ASCII: always 0)
            return max(needed, _MIN_ADU - started)
        return needed

    def wake_at(self, now: float, lead: float = 0.0) -> float | None:
        """Until when a driver that just gave the protocol all the bytes it could read
        (at ``now``) may sleep without watching the port, so that it wakes once for
        the rest of a frame instead of once per byte; None: watch the port.

        A request to this slave (or a broadcast) whose length the rules give
        (Application Protocol V1.1b section 6, and the registered rules; from the
        address alone, the last request's length up to 8 bytes; without a rule for
        its function, that function's last length): its end at the character rate,
        plus the turnaround when it will be answered, less ``lead`` (at most half
        the turnaround, so that the request is in): the driver reads the request,
        prepares the response during the turnaround and sends it at its time
        (`deadline`); with ``lead`` 0 it reads, executes and sends in one wake-up, a
        little late.  Any other frame in progress: ``needed()`` characters (the
        least it can still take).  Never more than half the flush timeout (a frame
        longer on the wire takes one wake-up more per such nap).  RTU only (ASCII
        frames end at a delimiter, not at a length); none while a response waits or
        an echo is due.

        The bytes the driver reads after the nap must be given to `receive_data`
        (even none): the frame they end is taken to have ended by its last byte's
        time at the character rate from ``now``, not by the late read (a frame is
        sent as a continuous stream, Serial Line V1.02 2.5.1.1), so the response
        still goes out t3.5 after the frame's end on the line, and the framer sees
        no silence inside it whatever the nap's excess over it.
        """
        head = self._head
        n = len(head)
        if n == 0 or not self._codec.by_length or self._pending is not None or self._echo:
            return None
        unit = head[0]
        char = self.char_time
        if unit == 0 or unit in self.app.addresses:
            length = 0
            if n >= 2:
                status, length = self._predict(bytes(head))
                if status == PRED_UNKNOWN:  # no rule: this function's last length
                    length = self._last_length if head[1] == self._last_function else 0
                elif status != PRED_LENGTH:  # the rule needs more bytes: needed()
                    length = 0
            else:
                # the function code is not in yet: guess the last request's length (a
                # master polls the same requests), but no more than _GUESS_MAX: a
                # guess too long answers late by what it is too long (past the
                # master's timeout, from a long write to a short read), one too short
                # costs one more wake-up; never an early answer (see receive_data)
                length = min(self._last_length, _GUESS_MAX)
            if n < length <= self.max_adu:
                end = now + (length - n) * char
                if unit != 0 and not self.state.listen_only:  # answered: the turnaround
                    turnaround = self.turnaround
                    end += turnaround - min(lead, 0.5 * turnaround)
                return self._sleep(now, length - n, end)
        need = self.needed()
        if need <= 0:
            return None
        return self._sleep(now, need, now + need * char)

    def _sleep(self, now: float, count: int, until: float) -> float:
        """A nap from ``now`` for ``count`` more bytes until ``until``, or the longest
        nap (`_nap_limit`, and as many bytes as come in it): when it ends."""
        limit = now + self._nap_limit
        if until > limit:
            until = limit
            count = min(count, int(self._nap_limit / self.char_time))
        self._nap = (now, self._received, count)
        return until

    @property
    def pending(self) -> Response | None:
        """The response waiting for its time, if any."""
        return self._pending

    def data_to_send(self, now: float) -> bytes | None:
        """The response ADU if its time has come (the caller writes it now), else None."""
        pending = self._pending
        if pending is None or now < pending.earliest:
            return None
        self._pending = None
        self._sending = pending
        self._core.sent(pending.adu)
        self.state.answered(pending.exception)
        self.counters["exceptions" if pending.exception is not None else "responses"] += 1
        if log.isEnabledFor(logging.DEBUG):
            log.debug("TX unit %d: %s", pending.unit, pending.adu.hex(" "))
        return pending.adu

    def next_action(
        self, now: float, *, lead: float = 0.0, nap: bool = True, ahead: float = 0.0
    ) -> ServerAction:
        """What the driver does next, at ``now``: the one entry point of a driver.

        Lets the time up to ``now`` act (`handle_timer`), then: `Reply` when a
        response's time has come (it is handed out: write it, then `transmitted`);
        after new bytes, `Listen` with ``needed`` > 0 when the driver may sleep
        through the rest of a frame (``nap``: the driver can, e.g. a port with a file
        descriptor in lenient mode; ``lead``: see `wake_at`); else `Listen` until the
        next deadline (`deadline`), or `Idle` when only bytes will do.  ``ahead``: a
        driver that can write at a given time (`pyrtu.drivers.xfer`'s xfer runners) gets
        the response that long before its time, as a `Reply` whose ``at`` is still
        to come, and a `Listen` that ends then."""
        fresh, self._fresh = self._fresh, False
        due = self.deadline()
        if due is not None and now >= due:
            self.handle_timer(now)
        pending = self._pending
        if pending is not None and now >= pending.earliest - ahead:
            self.data_to_send(max(now, pending.earliest))
            return Reply(pending.adu, pending.earliest)
        if fresh and nap:
            until = self.wake_at(now, lead)
            if until is not None:
                assert self._nap is not None
                return Listen(until, max(1, self._nap[2]))
        due = self.deadline()
        if pending is not None and ahead and due is not None and pending.earliest <= due:
            due = pending.earliest - ahead
        return _IDLE if due is None else Listen(due)

    # ------------------------------------------------------------------ frames

    def _core_events(self, now: float) -> None:
        """The core's events, (offset, length, kind, error, start_us, end_us, adu)."""
        poll = self._core.poll
        while (ev := poll()) is not None:
            offset, length, kind, error, start_us, end_us, adu = ev
            self._framed = offset + length
            if error:
                reason = ERROR_BY_CODE[error]
                assert reason is not None
                self.state.discard_seen(reason.value, start_us / 1e6, end_us / 1e6)
            else:
                self._on_frame(kind, adu, self._message(adu), offset, end_us / 1e6, now)

    def _on_frame(
        self, kind: int, raw: bytes, message: bytes, offset: int, end: float | None, now: float
    ) -> None:
        """A frame checked by its CRC or LRC: ``raw`` as on the wire, ``message`` the
        address and PDU, ``kind`` a `FrameKind` (RTU_KIND_*), ``end`` its last byte's
        time (None: no times given)."""
        if self._echo is not None:
            sent, self._echo = self._echo, None
            if raw == sent and now <= self._echo_until:
                self.counters["echo_dropped"] += 1
                return
        self.state.frame_seen()
        if kind != _REQUEST:
            return
        unit = message[0]
        if unit != 0 and unit not in self.app.addresses:
            self.counters["ignored"] += 1
            return
        broadcast = unit == 0
        self._last_length = len(raw)  # (used by wake_at: RTU only)
        self._last_function = raw[1]
        request = message[1:]
        self.state.request_received(broadcast)
        self.counters["broadcasts" if broadcast else "requests"] += 1
        self._last_valid = now
        self._tripped = False
        if log.isEnabledFor(logging.DEBUG):
            log.debug("RX unit %d: %s", unit, raw.hex(" "))
        if self.state.listen_only:
            if request[:3] == b"\x08\x00\x01":  # restart: the one request served
                with contextlib.suppress(SlaveException):  # not answered either way
                    self.state.diagnostics(request)
            self.state.not_answered()
            return
        response = self.app.execute(unit, request)
        if broadcast or response is None:
            self.state.not_answered()
            return
        if self._pending is not None:
            self.state.not_answered()
        late = self._late
        if late is not None and late[0] <= offset and offset + len(raw) <= late[1]:
            end = late[2]  # a frame all in the bytes read after a nap: see receive_data
        elif end is None:
            end = now
        self._pending = Response(
            unit,
            self._encode(bytes((unit,)) + response),
            end + self.turnaround + self.response_delay,
            response[1] if response[0] & 0x80 else None,
        )


__all__ = [
    "Application",
    "Idle",
    "Listen",
    "Reply",
    "Response",
    "ServerAction",
    "ServerProtocol",
    "WatchedApplication",
]
