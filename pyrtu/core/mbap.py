"""The Python face of MBAP framing (Modbus TCP), shared by both backends.

Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: an ADU is the
7-byte MBAP header (transaction id, protocol id 0, length = unit id + PDU, unit
id) and the PDU.  A backend supplies a *core* for the incremental framer
(``feed(data) -> int``, ``close()``, ``poll() -> event``, ``needed() -> int``,
``error() -> int``, ``counts()``), ``encode(transaction, unit, pdu)`` and a
bulk ``parse(role, data) -> MbapFrameList``; arguments are checked here, once,
so both backends raise the same exceptions.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from pyrtu.core._types import BytesLike
from pyrtu.core.feed import feed_all
from pyrtu.core.frames import FrameKind, LazyFrames, Reason
from pyrtu.core.framing import EventQueue, as_bytes, public
from pyrtu.core.options import ROLES

HEADER_LEN = 7
MIN_LENGTH = 2  # unit id + a PDU of at least the function code
MAX_LENGTH = 254  # unit id + a PDU of 253 bytes (Application Protocol 4.1)
MAX_PDU = MAX_LENGTH - 1
MAX_ADU = 6 + MAX_LENGTH
#: an MBAP header and its unit id ([TCP] 3.1.3): transaction id, protocol id (0),
#: length (unit id + PDU), unit id; ``pack(tid, 0, len(pdu) + 1, unit) + pdu`` is the ADU
MBAP_HEADER = struct.Struct(">HHHB")


# (offset, length, kind, error, adu)
MbapEvent = tuple[int, int, int, int, bytes]


class MbapError(Reason):
    """Why bytes of a Modbus TCP stream were discarded."""

    PROTOCOL = "protocol_id"  # protocol id other than 0: not Modbus
    LENGTH = "length"  # length field outside 2..254
    TRUNCATED = "truncated"  # the stream ended inside an ADU


#: The C core's RTU_MBAP_ERR_* codes in order; index 0 is "no error".
MBAP_ERROR_BY_CODE: tuple[MbapError | None, ...] = (
    None,
    MbapError.PROTOCOL,
    MbapError.LENGTH,
    MbapError.TRUNCATED,
)


@dataclass(frozen=True, slots=True)
class MbapFrame:
    """A Modbus TCP ADU, or a discard event (``error`` set) from the MBAP framer.

    ``adu`` is the bytes as on the wire: the 7-byte MBAP header and the PDU (for a
    discard event, the discarded bytes).  ``offset`` is the position of its first
    byte in the stream.  Header fields read from a discard event are those of the
    bytes there are (-1 where the bytes are missing).
    """

    kind: FrameKind
    adu: bytes
    offset: int = 0
    error: MbapError | None = None

    def _u16(self, at: int) -> int:
        return (self.adu[at] << 8) | self.adu[at + 1] if len(self.adu) >= at + 2 else -1

    @property
    def transaction(self) -> int:
        return self._u16(0)

    @property
    def protocol(self) -> int:
        return self._u16(2)

    @property
    def length(self) -> int:
        """The header's length field: unit id + PDU."""
        return self._u16(4)

    @property
    def unit(self) -> int:
        return self.adu[6] if len(self.adu) > 6 else -1

    @property
    def function(self) -> int:
        return self.adu[7] if len(self.adu) > 7 else -1

    @property
    def pdu(self) -> bytes:
        return self.adu[HEADER_LEN:] if self.error is None else b""

    @property
    def exception_code(self) -> int | None:
        """The exception code of an exception response, else None."""
        if self.kind is FrameKind.EXCEPTION and len(self.adu) > HEADER_LEN + 1:
            return self.adu[HEADER_LEN + 1]
        return None

    def __repr__(self) -> str:
        if self.error is not None:
            what = f"error={self.error}, length={len(self.adu)}"
        else:
            what = f"transaction={self.transaction}, unit={self.unit}, pdu={self.pdu.hex(' ')}"
        return f"MbapFrame({self.kind}, {what}, offset={self.offset})"


#: FrameKind by the core's code: an index, not an Enum call per frame
_KIND_BY_CODE = tuple(FrameKind(k) for k in range(len(FrameKind)))


def event_to_mbap_frame(ev: MbapEvent) -> MbapFrame:
    offset, _length, kind, error, adu = ev
    return MbapFrame(_KIND_BY_CODE[kind], adu, offset, MBAP_ERROR_BY_CODE[error])


def mbap_counters_dict(
    frames: Sequence[int], discarded: Sequence[int], events: int
) -> dict[str, int]:
    """Frames by kind, discard events, discarded bytes by reason."""
    out = {
        str(kind): int(frames[kind])
        for kind in (FrameKind.REQUEST, FrameKind.RESPONSE, FrameKind.EXCEPTION, FrameKind.UNKNOWN)
    }
    out["discard_events"] = int(events)
    for code, reason in enumerate(MBAP_ERROR_BY_CODE):
        if reason is not None:
            out[f"discarded_{reason.value}"] = int(discarded[code])
    return out


def check_role(role: str) -> int:
    if role not in ROLES:
        raise ValueError(f"role must be 'master', 'slave' or 'monitor', not {role!r}")
    return ROLES[role]


def check_header_args(transaction: int, unit: int, pdu: BytesLike) -> bytes:
    """Validate the arguments of an ADU; returns the PDU as bytes."""
    if isinstance(transaction, bool) or not isinstance(transaction, int):
        raise TypeError(f"transaction must be an integer, not {type(transaction).__name__}")
    if not 0 <= transaction <= 0xFFFF:
        raise ValueError(f"transaction must be 0..65535, not {transaction}")
    if isinstance(unit, bool) or not isinstance(unit, int):
        raise TypeError(f"unit must be an integer, not {type(unit).__name__}")
    if not 0 <= unit <= 0xFF:
        raise ValueError(f"unit must be 0..255, not {unit}")
    raw = as_bytes(pdu, "pdu")
    if not 1 <= len(raw) <= MAX_PDU:
        raise ValueError(f"pdu must be 1..{MAX_PDU} bytes, not {len(raw)}")
    return raw


class MbapCore(Protocol):
    def feed(self, data: bytes) -> int: ...
    def close(self) -> None: ...
    def poll(self) -> MbapEvent | None: ...
    def needed(self) -> int: ...
    def error(self) -> int: ...
    def counts(self) -> tuple[Sequence[int], Sequence[int], int]: ...


class MbapFramerBase(EventQueue[MbapFrame]):
    """A sans-I/O Modbus TCP stream (in the spirit of h11): one direction of a connection.

    ``receive_data(data)`` takes bytes as read from the socket, in any pieces;
    ``receive_data(b"")`` says the stream ended (an incomplete ADU becomes a
    ``truncated`` discard event).  ``next_event()`` returns `MbapFrame` events until
    None.  A header that breaks the rules (protocol id not 0, length outside
    2..254) cannot be skipped over on a TCP stream: it gives one discard event and
    ``error`` is set from then on (a server closes that connection; every later byte
    is counted as discarded).  ``send(transaction, unit, pdu)`` returns the bytes
    to write.  Roles: ``"master"`` reads responses (client side), ``"slave"`` reads
    requests (server side), ``"monitor"`` either.
    """

    BACKEND = ""

    def __init__(self, role: str = "slave") -> None:
        self.role = role
        self._core = self._make_core(check_role(role))
        self._events: deque[MbapFrame] = deque()
        self._eof = False

    def _make_core(self, role: int) -> MbapCore:
        raise NotImplementedError

    def _encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
        raise NotImplementedError

    def _drain(self) -> None:
        poll, append = self._core.poll, self._events.append
        while (ev := poll()) is not None:
            append(event_to_mbap_frame(ev))

    def receive_data(self, data: BytesLike) -> None:
        """Bytes read from the stream; ``b""`` at its end."""
        raw = as_bytes(data)
        if self._eof:
            if raw:
                raise RuntimeError("MbapFramer: data received after the end of the stream")
            return
        if not raw:
            self._eof = True
            self._core.close()
            self._drain()
            return
        feed_all(self._core.feed, raw, self._drain)

    @property
    def needed(self) -> int:
        """Bytes still needed to complete the ADU being received (7 when idle; 0 when
        the stream has ended or failed)."""
        return self._core.needed()

    @property
    def error(self) -> MbapError | None:
        """Why the stream can no longer be framed, or None."""
        return MBAP_ERROR_BY_CODE[self._core.error()]

    def send(self, transaction: int, unit: int, pdu: BytesLike) -> bytes:
        """The ADU carrying ``pdu`` to ``unit`` under ``transaction``: the bytes to write."""
        return self._encode(transaction, unit, check_header_args(transaction, unit, pdu))

    @property
    def counters(self) -> dict[str, int]:
        """Frames by kind, discard events and discarded bytes by reason."""
        return mbap_counters_dict(*self._core.counts())


def make_mbap_framer(
    backend: str,
    make_core: Callable[[int], MbapCore],
    encode: Callable[[int, int, bytes], bytes],
) -> type[MbapFramerBase]:
    """The public MbapFramer class of a backend, around its ``make_core(role)`` and its
    ``encode(transaction, unit, pdu)``."""

    class MbapFramer(MbapFramerBase):
        __doc__ = MbapFramerBase.__doc__
        BACKEND = backend

        def _make_core(self, role: int) -> MbapCore:
            return make_core(role)

        def _encode(self, transaction: int, unit: int, pdu: bytes) -> bytes:
            return encode(transaction, unit, pdu)

    MbapFramer.__qualname__ = MbapFramer.__name__
    MbapFramer.__module__ = make_core.__module__  # the backend's module
    return MbapFramer


class MbapFrameList(LazyFrames[MbapFrame]):
    """A lazy sequence of the ADUs and discard events of a Modbus TCP capture.

    Backed by compact arrays (offset, length, kind, error per entry); ``len()`` is
    immediate and MbapFrame objects are built only when an item is read.
    Subclasses provide ``_entry(i)``; ``counters`` as the framer's.
    """

    counters: dict[str, int]
    _data: bytes

    def __init__(self, data: bytes, count: int) -> None:
        super().__init__(data, count)

    def _name(self) -> str:
        return MbapFrameList.__name__

    def _entry(self, i: int) -> tuple[int, int, int, int]:
        raise NotImplementedError

    def _make(self, i: int) -> MbapFrame:
        offset, length, kind, error = self._entry(i)
        return MbapFrame(
            kind=FrameKind(kind),
            adu=self._data[offset : offset + length],
            offset=offset,
            error=MBAP_ERROR_BY_CODE[error],
        )


def make_parse_tcp_stream(
    parse: Callable[[int, bytes], MbapFrameList],
) -> Callable[..., MbapFrameList]:
    """The public parse_tcp_stream of a backend, around its ``parse(role, data)``."""

    def parse_tcp_stream(data: BytesLike, role: str = "monitor") -> MbapFrameList:
        """Every ADU of ``data`` (one direction of a Modbus TCP connection), lazily.

        The length field delimits the ADUs.  A bad header (protocol id not 0,
        length outside 2..254) ends the framing: the rest of the capture is one
        discard event with that reason; an ADU cut by the end of the capture is a
        ``truncated`` discard event.  ``role`` as for `MbapFramer` (``"master"``:
        the server's answers, ``"slave"``: the client's requests).
        """
        code = check_role(role)
        return parse(code, as_bytes(data))

    return public(parse_tcp_stream)


def make_encode_mbap(
    encode: Callable[[int, int, bytes], bytes],
) -> Callable[[int, int, BytesLike], bytes]:
    """The public encode_mbap of a backend, around its ``encode(transaction, unit, pdu)``."""

    def encode_mbap(transaction: int, unit: int, pdu: BytesLike) -> bytes:
        """MBAP header (protocol id 0, length = 1 + len(pdu)) and ``pdu``."""
        return encode(transaction, unit, check_header_args(transaction, unit, pdu))

    return public(encode_mbap)


class MbapNames(NamedTuple):
    """The public MBAP names of a backend (`backend_mbap`)."""

    MbapFramer: type[MbapFramerBase]
    parse_tcp_stream: Callable[..., MbapFrameList]
    encode_mbap: Callable[[int, int, BytesLike], bytes]


def backend_mbap(
    backend: str,
    make_core: Callable[[int], MbapCore],
    encode: Callable[[int, int, bytes], bytes],
    parse: Callable[[int, bytes], MbapFrameList],
) -> MbapNames:
    """The public MbapFramer class, parse_tcp_stream and encode_mbap of a backend, around
    its ``make_core(role)``, its ``encode(transaction, unit, pdu)`` and its
    ``parse(role, data)``."""
    return MbapNames(
        make_mbap_framer(backend, make_core, encode),
        make_parse_tcp_stream(parse),
        make_encode_mbap(encode),
    )
