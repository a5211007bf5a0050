"""Modbus ASCII framing: ':' + hex of (address, PDU) + LRC + CR LF.

Modbus over Serial Line V1.02, 2.5.2: each byte is sent as two uppercase hex
characters; the LRC (6.2.1) covers the binary bytes; a frame starts with ':'
and ends with CR LF; characters may be up to one second apart (2.5.2.1).
"""

from __future__ import annotations

import binascii
from collections import deque
from collections.abc import Sequence
from types import ModuleType
from typing import Any

from pyrtu.core._backend import active
from pyrtu.core._types import BytesLike
from pyrtu.core.frames import CODE_BY_ERROR, ERROR_BY_CODE, ErrorReason, Frame, FrameKind
from pyrtu.core.framing import Event, EventQueue
from pyrtu.core.line import LineConfig
from pyrtu.core.options import ROLES, to_microseconds
from pyrtu.core.timing import positive_seconds

ASCII_MAX_FRAME = 513  # ':' + 2 x 255 + CR LF (2.5.2.1)
INTER_CHAR_LIMIT = 1.0  # seconds (2.5.2.1)


def _lrc(data: bytes) -> int:
    return int(active.lrc(data))


def encode_ascii(message: BytesLike) -> bytes:
    """The ASCII frame of ``message`` (address + PDU, no checksum)."""
    raw = memoryview(message).cast("B").tobytes()
    if len(raw) < 2:
        raise ValueError(f"encode_ascii: a message has an address and a function, got {raw!r}")
    body = raw + bytes((_lrc(raw),))
    return b":" + binascii.hexlify(body).upper() + b"\r\n"


def decode_ascii(frame: BytesLike) -> bytes:
    """Address + PDU from an ASCII frame; ValueError naming what is wrong."""
    raw = memoryview(frame).cast("B").tobytes()
    if not raw.startswith(b":"):
        raise ValueError(f"decode_ascii: frame must start with ':', got {raw[:1]!r}")
    if not raw.endswith(b"\r\n"):
        raise ValueError("decode_ascii: frame must end with CR LF")
    text = raw[1:-2]
    if len(text) % 2 or len(text) < 6:
        raise ValueError(f"decode_ascii: {len(text)} hex characters is not a frame")
    try:
        body = binascii.unhexlify(text)
    except binascii.Error:
        raise ValueError(f"decode_ascii: not hexadecimal: {text!r}") from None
    message, check = body[:-1], body[-1]
    expected = _lrc(message)
    if check != expected:
        raise ValueError(f"decode_ascii: LRC is {check:02X}, expected {expected:02X}")
    return message


def make_framer(line: LineConfig, role: str = "master", backend: ModuleType | None = None) -> Any:
    """The receiver for ``line``: the RTU ``Framer`` of ``backend`` (default: the active
    backend) or, in ASCII mode, an `AsciiFramer`; both yield `Frame` events."""
    if line.mode == "ascii":
        return AsciiFramer(role, line=line)
    return (backend or active).Framer(role, line=line)


class AsciiCore:
    """The ASCII framer core, with the RTU core's feed/take interface (`FramerCore`):
    ``feed(data, now_us) -> int``, ``poll()`` / ``take()``, ``handle_timer(now_us)``,
    ``deadline()``, ``sent``, ``expect``, ``reset``, ``needed``, ``counts``.

    Frames are delimited by ':' and CR LF; a ':' restarts a frame (2.5.2.1); a
    silence of more than ``inter_char_us`` inside a frame discards it.  An event's
    ``adu`` is the characters as on the wire: a whole frame (its LRC checked) or
    the characters thrown away; a run of characters outside any frame is one
    discard event.  The buffer holds one frame at most (`ASCII_MAX_FRAME`); the
    events of one feed are bounded by its bytes.
    """

    def __init__(self, role: str, inter_char_us: int) -> None:
        self.role = role
        self.inter_char_us = inter_char_us
        self._buf = bytearray()
        self._in_frame = False
        self._start_us = 0
        self._last_us: int | None = None
        self._offset = 0  # bytes taken before the one being looked at
        self._events: deque[Event] = deque()
        self._pending: tuple[int, int] | None = None  # monitor: the request's (unit, fc)
        self._frames = [0, 0, 0, 0]
        self._discarded = [0] * len(ERROR_BY_CODE)
        self._discard_events = 0

    def _discard(self, raw: bytes, reason: ErrorReason, start_us: int, end_us: int) -> None:
        self._discarded[CODE_BY_ERROR[reason]] += len(raw)
        self._discard_events += 1
        ev = (self._offset - len(raw), len(raw), FrameKind.DISCARD.value,
              CODE_BY_ERROR[reason], start_us, end_us, raw)  # fmt: skip
        self._events.append(ev)

    def _kind(self, message: bytes) -> FrameKind:
        if message[1] & 0x80:
            return FrameKind.EXCEPTION
        if self.role == "master":
            return FrameKind.RESPONSE
        p = self._pending
        if self.role == "monitor" and p is not None and (message[0], message[1]) == p:
            return FrameKind.RESPONSE
        return FrameKind.REQUEST

    def _silence(self, now_us: int) -> None:
        """A silence longer than the inter-character limit discards the frame."""
        last = self._last_us
        if self._in_frame and last is not None and now_us - last > self.inter_char_us:
            self._discard(bytes(self._buf), ErrorReason.T15, self._start_us, last)
            self._buf.clear()
            self._in_frame = False

    def feed(self, data: bytes, now_us: int) -> int:
        """Takes all of ``data`` (arrived by ``now_us``)."""
        self._silence(now_us)
        buf = self._buf
        stray = -1  # where a run of characters outside a frame began in data
        for i, byte in enumerate(data):
            if byte == 0x3A:  # ':' starts (or restarts) a frame
                if stray >= 0:
                    self._discard(data[stray:i], ErrorReason.TRUNCATED, now_us, now_us)
                    stray = -1
                if buf:
                    self._discard(bytes(buf), ErrorReason.TRUNCATED, self._start_us, now_us)
                buf[:] = b":"
                self._in_frame = True
                self._start_us = now_us
            elif not self._in_frame:
                if stray < 0:
                    stray = i
            else:
                buf.append(byte)
                if len(buf) > ASCII_MAX_FRAME:
                    self._offset += 1
                    self._discard(bytes(buf), ErrorReason.OVERFLOW, self._start_us, now_us)
                    self._offset -= 1
                    buf.clear()
                    self._in_frame = False
                elif byte == 0x0A and buf.endswith(b"\r\n"):
                    self._offset += 1
                    self._finish(bytes(buf), now_us)
                    self._offset -= 1
                    buf.clear()
                    self._in_frame = False
            self._offset += 1
        if stray >= 0:
            self._discard(data[stray:], ErrorReason.TRUNCATED, now_us, now_us)
        if data:
            self._last_us = now_us
        return len(data)

    def _finish(self, raw: bytes, now_us: int) -> None:
        try:
            message = decode_ascii(raw)
        except ValueError:
            self._discard(raw, ErrorReason.CRC, self._start_us, now_us)
            return
        kind = self._kind(message)
        if kind is FrameKind.REQUEST and message[0] != 0:
            self._pending = (message[0], message[1])
        elif kind is not FrameKind.REQUEST:
            self._pending = None
        self._frames[kind] += 1
        ev = (self._offset - len(raw), len(raw), kind.value, 0, self._start_us, now_us, raw)
        self._events.append(ev)

    def poll(self) -> Event | None:
        """The next event: (offset, length, kind, error, start_us, end_us, adu)."""
        return self._events.popleft() if self._events else None

    def take(self) -> tuple[int, int, bytes] | None:
        """The next event as (error, end_us, adu)."""
        if not self._events:
            return None
        ev = self._events.popleft()
        return ev[3], ev[5], ev[6]

    def deadline(self) -> int | None:
        """The first microsecond at which `handle_timer` discards the frame in progress."""
        if not self._in_frame or self._last_us is None:
            return None
        return self._last_us + self.inter_char_us + 1

    def handle_timer(self, now_us: int) -> None:
        self._silence(now_us)

    def sent(self, adu: bytes) -> None:
        """ASCII frames carry their own delimiters: nothing to predict."""

    def expect(self, adu: bytes) -> None:
        """``reset()`` then ``sent(adu)``, as the RTU core's: a fresh framer for the
        answer to ``adu``."""
        self.reset()

    def needed(self) -> int:
        """0: ASCII frames end at CR LF, not at a predicted length (wake on any byte)."""
        return 0

    def reset(self) -> None:
        self._buf.clear()
        self._in_frame = False
        self._events.clear()
        self._pending = None

    def counts(self) -> tuple[Sequence[int], Sequence[int], int]:
        return self._frames, self._discarded, self._discard_events


def ascii_message(wire: bytes) -> bytes:
    """Address + PDU of a frame `AsciiCore` checked (``wire``: as on the line)."""
    return binascii.unhexlify(wire[1:-4])


_TABLES: dict[int, bytes] = {}


def delimiter_table(char: int) -> bytes:
    """Incoming bytes with ``char`` as the frame end (FC 08 sub-function 0x03)."""
    table = _TABLES.get(char)
    if table is None:
        mapping = bytearray(range(256))
        mapping[char] = 0x0A
        mapping[0x0A] = 0x00  # a LF is no longer a delimiter: it breaks the frame
        table = _TABLES[char] = bytes(mapping)
    return table


class AsciiFramer(EventQueue[Frame]):
    """Sans-I/O receiver for ASCII mode, with the same face as ``Framer``.

    Frames are delimited by ':' and CR LF; a ':' restarts a frame (2.5.2.1);
    a silence of more than ``inter_char`` seconds inside a frame discards it.
    Events are the same `Frame` objects as the RTU framer's: ``adu`` is the
    binary address + PDU + LRC, ``message``/``pdu`` as in RTU, ``text`` the
    frame as received; a discard event's ``adu`` and ``text`` hold the
    characters thrown away.  ``core``: its `AsciiCore` (the feed/take interface
    the protocols drive, as the RTU framer's).
    """

    def __init__(
        self,
        role: str = "master",
        *,
        inter_char: float = INTER_CHAR_LIMIT,
        line: LineConfig | None = None,
    ) -> None:
        if role not in ROLES:
            raise ValueError(f"role must be 'master', 'slave' or 'monitor', not {role!r}")
        if line is not None:
            if not isinstance(line, LineConfig):
                raise TypeError(f"line must be a LineConfig, not {type(line).__name__}")
            inter_char = line.inter_char
        else:
            positive_seconds(inter_char, "inter_char")
        self.role = role
        self.line = line
        self.inter_char_us = to_microseconds(inter_char)
        self.core = AsciiCore(role, self.inter_char_us)
        self._events: deque[Frame] = deque()

    def _drain(self) -> None:
        append = self._events.append
        while (ev := self.core.poll()) is not None:
            offset, _length, kind, error, start_us, end_us, wire = ev
            reason = ERROR_BY_CODE[error]
            adu = wire if reason is not None else binascii.unhexlify(wire[1:-2])
            append(Frame(FrameKind(kind), adu, offset, start_us / 1e6, end_us / 1e6, reason, wire))

    def receive_data(self, data: BytesLike, now: float) -> None:
        self.core.feed(memoryview(data).cast("B").tobytes(), to_microseconds(now))
        self._drain()

    def send(self, frame: BytesLike) -> bytes:
        """Record that ``frame`` (an ASCII frame) is transmitted by this side; returns
        the bytes to write.  (ASCII frames carry their own delimiters: nothing to
        predict.)"""
        return memoryview(frame).cast("B").tobytes()

    def needed(self) -> int:
        """0: ASCII frames end at CR LF, not at a predicted length (wake on any byte)."""
        return 0

    def timer(self) -> float | None:
        """When `handle_timer` discards the frame in progress (None: no frame)."""
        deadline = self.core.deadline()
        return None if deadline is None else deadline / 1e6

    def handle_timer(self, now: float) -> None:
        self.core.handle_timer(to_microseconds(now))
        self._drain()

    def restart(self, frame: bytes | None = None) -> None:
        """``reset()`` for a new transaction (``frame``: what was sent; unused)."""
        self.reset()

    def reset(self) -> None:
        self.core.reset()
        self._events.clear()

    @property
    def counters(self) -> dict[str, int]:
        """Frames, discarded characters and frames whose LRC failed, since creation."""
        frames, discarded, _events = self.core.counts()
        return {
            "frames": sum(frames),
            "discarded_bytes": sum(discarded),
            "lrc_errors": discarded[CODE_BY_ERROR[ErrorReason.CRC]],
        }


__all__ = [
    "ASCII_MAX_FRAME",
    "INTER_CHAR_LIMIT",
    "AsciiCore",
    "AsciiFramer",
    "ascii_message",
    "decode_ascii",
    "delimiter_table",
    "encode_ascii",
    "make_framer",
]
