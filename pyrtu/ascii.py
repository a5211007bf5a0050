"""Modbus ASCII framing: ':' + hex of (address, PDU) + LRC + CR LF.

Modbus over Serial Line V1.02, 2.5.2: each byte is sent as two uppercase hex
characters; the LRC (6.2.1) covers the binary bytes; a frame starts with ':'
and ends with CR LF; characters may be up to one second apart (2.5.2.1).
"""

from __future__ import annotations

import binascii
from collections import deque
from types import ModuleType
from typing import Any

from ._backend import active
from ._types import BytesLike
from .config import ROLES, to_microseconds
from .frames import ErrorReason, Frame, FrameKind
from .line import LineConfig

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


class AsciiFramer:
    """Sans-I/O receiver for ASCII mode, with the same face as ``Framer``.

    Frames are delimited by ':' and CR LF; a ':' restarts a frame (2.5.2.1);
    a silence of more than ``inter_char`` seconds inside a frame discards it.
    Events are the same `Frame` objects as the RTU framer's: ``adu`` is the
    binary address + PDU + LRC, ``message``/``pdu`` as in RTU, ``text`` the
    frame as received; a discard event's ``adu`` and ``text`` hold the
    characters thrown away.
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
        elif (
            isinstance(inter_char, bool)
            or not isinstance(inter_char, int | float)
            or not 0 < inter_char < float("inf")
        ):
            raise ValueError(f"inter_char must be a positive number of seconds, not {inter_char!r}")
        self.role = role
        self.line = line
        self.inter_char_us = to_microseconds(inter_char)
        self._buf = bytearray()
        self._in_frame = False
        self._start_us = 0
        self._last_us: int | None = None
        self._offset = 0
        self._events: deque[Frame] = deque()
        self._pending: tuple[int, int] | None = None
        self.counters = {"frames": 0, "discarded_bytes": 0, "lrc_errors": 0}

    def _discard(self, raw: bytes, reason: ErrorReason, end_us: int) -> None:
        if not raw:
            return
        self.counters["discarded_bytes"] += len(raw)
        frame = Frame(
            FrameKind.DISCARD,
            raw,
            self._offset - len(raw),
            self._start_us / 1e6,
            end_us / 1e6,
            reason,
            raw,
        )
        self._events.append(frame)

    def _kind(self, message: bytes) -> FrameKind:
        if message[1] & 0x80:
            return FrameKind.EXCEPTION
        if self.role == "master":
            return FrameKind.RESPONSE
        p = self._pending
        if self.role == "monitor" and p is not None and (message[0], message[1]) == p:
            return FrameKind.RESPONSE
        return FrameKind.REQUEST

    def receive_data(self, data: BytesLike, now: float) -> None:
        now_us = to_microseconds(now)
        for byte in memoryview(data).cast("B").tobytes():
            self._offset += 1
            if (
                self._in_frame
                and self._last_us is not None
                and now_us - self._last_us > self.inter_char_us
            ):
                self._discard(bytes(self._buf), ErrorReason.T15, self._last_us)
                self._buf.clear()
                self._in_frame = False
            self._last_us = now_us
            if byte == 0x3A:  # ':' starts (or restarts) a frame
                if self._buf:
                    self._discard(bytes(self._buf), ErrorReason.TRUNCATED, now_us)
                self._buf = bytearray(b":")
                self._in_frame = True
                self._start_us = now_us
                continue
            if not self._in_frame:
                self._discard(bytes((byte,)), ErrorReason.TRUNCATED, now_us)
                continue
            self._buf.append(byte)
            if len(self._buf) > ASCII_MAX_FRAME:
                self._discard(bytes(self._buf), ErrorReason.OVERFLOW, now_us)
                self._buf.clear()
                self._in_frame = False
            elif self._buf.endswith(b"\r\n"):
                self._finish(bytes(self._buf), now_us)
                self._buf.clear()
                self._in_frame = False

    def _finish(self, raw: bytes, now_us: int) -> None:
        try:
            message = decode_ascii(raw)
        except ValueError:
            self.counters["lrc_errors"] += 1
            self._discard(raw, ErrorReason.CRC, now_us)
            return
        kind = self._kind(message)
        if kind is FrameKind.REQUEST and message[0] != 0:
            self._pending = (message[0], message[1])
        elif kind is not FrameKind.REQUEST:
            self._pending = None
        self.counters["frames"] += 1
        lrc = raw[-4:-2]
        frame = Frame(
            kind,
            message + bytes((int(lrc, 16),)),
            self._offset - len(raw),
            self._start_us / 1e6,
            now_us / 1e6,
            None,
            raw,
        )
        self._events.append(frame)

    def next_event(self) -> Frame | None:
        """The next `Frame` (a frame or a discard event), or None."""
        return self._events.popleft() if self._events else None

    def events(self) -> list[Frame]:
        """All events available now."""
        out = list(self._events)
        self._events.clear()
        return out

    def send(self, frame: BytesLike) -> bytes:
        """Record that ``frame`` (an ASCII frame) is transmitted by this side; returns
        the bytes to write.  (ASCII frames carry their own delimiters: nothing to
        predict.)"""
        return memoryview(frame).cast("B").tobytes()

    def needed(self) -> int:
        """0: ASCII frames end at CR LF, not at a predicted length (wake on any byte)."""
        return 0

    def timer(self) -> float | None:
        if not self._in_frame or self._last_us is None:
            return None
        return (self._last_us + self.inter_char_us) / 1e6

    def handle_timer(self, now: float) -> None:
        now_us = to_microseconds(now)
        if (
            self._in_frame
            and self._last_us is not None
            and now_us - self._last_us > self.inter_char_us
        ):
            self._discard(bytes(self._buf), ErrorReason.T15, self._last_us)
            self._buf.clear()
            self._in_frame = False

    def restart(self, frame: bytes | None = None) -> None:
        """``reset()`` for a new transaction (``frame``: what was sent; unused)."""
        self.reset()

    def reset(self) -> None:
        self._buf.clear()
        self._in_frame = False
        self._events.clear()
        self._pending = None
