"""MBAP framing of a Modbus TCP stream in pure Python: the twin of csrc/rtu_mbap.c.

Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: the 7-byte MBAP
header (transaction id, protocol id 0, length = unit id + PDU, unit id), all
big-endian; Application Protocol 4.1: a PDU of 1..253 bytes, so length 2..254.
The length field is the only delimiter on a TCP stream, so a bad header ends the
framing (see the C file for the rules).
"""

from __future__ import annotations

from array import array

from pyrtu.core._pure.head import (
    KIND_DISCARD,
    KIND_EXCEPTION,
    KIND_REQUEST,
    KIND_RESPONSE,
    KIND_UNKNOWN,
    ROLE_MASTER,
    ROLE_SLAVE,
)
from pyrtu.core.mbap import HEADER_LEN, MAX_ADU, MAX_LENGTH, MIN_LENGTH, MbapEvent

FRAMER_CAP = 2 * MAX_ADU

COMPLETE = 0
NEED = 1
INVALID = 2

ERR_NONE = 0
ERR_PROTOCOL = 1
ERR_LENGTH = 2
ERR_TRUNCATED = 3
NERR = 4


def inspect(data: bytes | bytearray, start: int, n: int) -> tuple[int, int, int]:
    """(result, length, error) for the n bytes at data[start:]: as rtu_mbap_inspect."""
    if n >= 4 and (data[start + 2] or data[start + 3]):
        return INVALID, HEADER_LEN, ERR_PROTOCOL
    if n < 6:
        return NEED, HEADER_LEN, ERR_NONE
    length = (data[start + 4] << 8) | data[start + 5]
    if length < MIN_LENGTH or length > MAX_LENGTH:
        return INVALID, HEADER_LEN, ERR_LENGTH
    total = 6 + length
    return (COMPLETE if n >= total else NEED), total, ERR_NONE


def kind_of(role: int, function: int) -> int:
    exception = bool(function & 0x80)
    if role == ROLE_MASTER:
        return KIND_EXCEPTION if exception else KIND_RESPONSE
    if role == ROLE_SLAVE:
        return KIND_REQUEST
    return KIND_EXCEPTION if exception else KIND_UNKNOWN


def encode(transaction: int, unit: int, pdu: bytes) -> bytes:
    """Header + PDU; arguments checked by the caller (as rtu_mbap_encode's EINVAL)."""
    n = len(pdu) + 1
    return bytes((transaction >> 8, transaction & 0xFF, 0, 0, n >> 8, n & 0xFF, unit)) + pdu


class CoreMbapFramer:
    """The incremental framer: the twin of rtu_mbap_framer."""

    def __init__(self, role: int) -> None:
        self.role = role
        self.error = ERR_NONE
        self.eof = False
        self.buf = bytearray()
        self.head = 0
        self.base = 0
        self.frames = [0, 0, 0, 0]
        self.discarded = [0] * NERR
        self.discard_events = 0

    def feed(self, data: bytes) -> int:
        if self.error != ERR_NONE:
            self.discarded[self.error] += len(data)
            return len(data)
        if self.eof:
            return 0
        if self.head:
            del self.buf[: self.head]
            self.base += self.head
            self.head = 0
        take = min(len(data), FRAMER_CAP - len(self.buf))
        self.buf += data[:take] if take < len(data) else data
        return take

    def close(self) -> None:
        self.eof = True

    def _discard(self, error: int) -> MbapEvent:
        count = len(self.buf) - self.head
        ev = (self.base + self.head, count, KIND_DISCARD, error, bytes(self.buf[self.head :]))
        self.discarded[error] += count
        self.discard_events += 1
        self.head = len(self.buf)
        return ev

    def poll(self) -> MbapEvent | None:
        unresolved = len(self.buf) - self.head
        if unresolved == 0 or self.error != ERR_NONE:
            return None
        result, length, error = inspect(self.buf, self.head, unresolved)
        if result == INVALID:
            self.error = error
            return self._discard(error)
        if result == NEED:
            return self._discard(ERR_TRUNCATED) if self.eof else None
        at = self.head
        kind = kind_of(self.role, self.buf[at + HEADER_LEN])
        self.frames[kind] += 1
        self.head += length
        return (self.base + at, length, kind, ERR_NONE, bytes(self.buf[at : at + length]))

    def needed(self) -> int:
        if self.error != ERR_NONE or self.eof:
            return 0
        unresolved = len(self.buf) - self.head
        result, length, _ = inspect(self.buf, self.head, unresolved)
        return length - unresolved if result == NEED else 0


class CoreMbapParser:
    """The bulk parser: the twin of rtu_mbap_parser / rtu_mbap_parse."""

    def __init__(self, role: int) -> None:
        self.role = role
        self.frames = [0, 0, 0, 0]
        self.discarded = [0] * NERR
        self.discard_events = 0

    def parse(self, data: bytes) -> tuple[array[int], array[int], array[int], array[int]]:
        """(offsets, lengths, kinds, errors) of every entry, as compact arrays."""
        offsets = array("Q")
        lengths = array("Q")
        kinds = array("B")
        errors = array("B")
        pos = 0
        end = len(data)
        while pos < end:
            left = end - pos
            result, length, error = inspect(data, pos, left)
            offsets.append(pos)
            if result == COMPLETE:
                kind = kind_of(self.role, data[pos + HEADER_LEN])
                lengths.append(length)
                kinds.append(kind)
                errors.append(ERR_NONE)
                self.frames[kind] += 1
                pos += length
                continue
            if result != INVALID:
                error = ERR_TRUNCATED
            lengths.append(left)
            kinds.append(KIND_DISCARD)
            errors.append(error)
            self.discarded[error] += left
            self.discard_events += 1
            pos = end
        return offsets, lengths, kinds, errors
