"""Frames and discard events, shared by both backends."""

from __future__ import annotations

import enum
import operator
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar, overload


class FrameKind(enum.IntEnum):
    """What a frame is: the values are the C core's RTU_KIND_* codes."""

    REQUEST = 0
    RESPONSE = 1
    EXCEPTION = 2
    UNKNOWN = 3  # CRC checks, direction unknown (monitor role, unknown function)
    DISCARD = 4  # bytes thrown away; see Frame.error

    def __str__(self) -> str:
        return self.name.lower()


class Reason(str, enum.Enum):
    """A reason that is its own text: ``str(r)`` and ``r == "crc"`` both give the value
    (`ErrorReason`, `pyrtu.core.mbap.MbapError`)."""

    def __str__(self) -> str:
        return str.__str__(self)


class ErrorReason(Reason):
    """Why bytes were discarded."""

    CRC = "crc"
    T15 = "t1.5"
    OVERFLOW = "overflow"
    UNKNOWN_FUNCTION = "unknown_function"
    TRUNCATED = "truncated"


#: C error codes (RTU_ERR_*) in order; index 0 is "no error".
ERROR_BY_CODE: tuple[ErrorReason | None, ...] = (
    None,
    ErrorReason.CRC,
    ErrorReason.T15,
    ErrorReason.OVERFLOW,
    ErrorReason.UNKNOWN_FUNCTION,
    ErrorReason.TRUNCATED,
)
CODE_BY_ERROR = {reason: code for code, reason in enumerate(ERROR_BY_CODE) if reason}


@dataclass(frozen=True, slots=True)
class Frame:
    """A frame (CRC or LRC checked) or a discard event (``error`` set) from a framer.

    One type for RTU and ASCII.  ``adu`` is the binary frame: address, PDU and the
    check (the 2-byte CRC in RTU, the 1-byte LRC in ASCII); ``message`` is address
    + PDU and ``pdu`` the function code and data, in both modes.  ``text`` is the
    ASCII frame as on the wire (``:`` hex LRC CR LF), None in RTU; ``wire`` is the
    bytes as on the wire in either mode.  A discard event's ``adu`` (and ``text``
    in ASCII) holds the bytes thrown away as they were received.  ``start``/``end``
    are seconds on the clock of the times given to the framer (None when no times
    were given).  ``offset`` is the position of the first byte in the byte stream.
    """

    kind: FrameKind
    adu: bytes
    offset: int = 0
    start: float | None = None
    end: float | None = None
    error: ErrorReason | None = None
    text: bytes | None = None

    @property
    def address(self) -> int:
        return self.adu[0] if self.adu else -1

    @property
    def function(self) -> int:
        return self.adu[1] if len(self.adu) > 1 else -1

    @property
    def message(self) -> bytes:
        """Address + PDU (the ADU without its CRC or LRC); b"" for a discard event."""
        if self.error is not None:
            return b""
        return self.adu[:-1] if self.text is not None else self.adu[:-2]

    @property
    def pdu(self) -> bytes:
        """Function code + data; b"" for a discard event."""
        return self.message[1:]

    @property
    def wire(self) -> bytes:
        """The frame as on the wire: the ASCII text in ASCII mode, else ``adu``."""
        return self.adu if self.text is None else self.text

    @property
    def exception_code(self) -> int | None:
        """The exception code of an exception response, else None."""
        return self.adu[2] if self.kind is FrameKind.EXCEPTION else None

    def __repr__(self) -> str:
        what = f"error={self.error}" if self.error else f"address={self.address}"
        return (
            f"Frame({self.kind}, {what}, function={self.function}, "
            f"adu={self.adu.hex(' ')}, offset={self.offset})"
        )


KINDS: tuple[FrameKind, ...] = tuple(FrameKind)
_new = object.__new__
_SET = tuple(Frame.__dict__[name].__set__ for name in Frame.__slots__)


def make_frame(
    kind: int,
    adu: bytes,
    offset: int,
    start: float | None,
    end: float | None,
    error: int,
    text: bytes | None = None,
) -> Frame:
    """A `Frame` from the core's codes (``kind``: RTU_KIND_*, ``error``: RTU_ERR_*),
    built without the frozen dataclass's checked ``__init__`` (the framers' hot path:
    several times faster; the fields are those of ``Frame``, in order)."""
    frame = _new(Frame)
    set_kind, set_adu, set_offset, set_start, set_end, set_error, set_text = _SET
    set_kind(frame, KINDS[kind])
    set_adu(frame, adu)
    set_offset(frame, offset)
    set_start(frame, start)
    set_end(frame, end)
    set_error(frame, ERROR_BY_CODE[error])
    set_text(frame, text)
    return frame


def event_counters_template() -> dict[str, int]:
    """The keys of a framer's ``counters`` dict, all zero."""
    keys = [str(k) for k in FrameKind if k is not FrameKind.DISCARD]
    keys += ["discard_events"] + [f"discarded_{r.value}" for r in ErrorReason]
    return dict.fromkeys(keys, 0)


class _HasError(Protocol):
    @property
    def error(self) -> object: ...


F = TypeVar("F", bound=_HasError)


class LazyFrames(Sequence[F]):
    """A lazy sequence of frames and discard events over a capture's bytes: ``len()``
    is immediate and an item is built (``_make(i)``) only when it is read.  The base of
    `FrameList` (RTU/ASCII) and `pyrtu.MbapFrameList` (Modbus TCP)."""

    _data: bytes | memoryview

    def __init__(self, data: bytes | memoryview, count: int) -> None:
        self._data = data
        self._count = count

    def __len__(self) -> int:
        return self._count

    def _make(self, i: int) -> F:
        raise NotImplementedError

    def _name(self) -> str:
        """The public class's name, for messages (not the backend's subclass)."""
        return LazyFrames.__name__

    @overload
    def __getitem__(self, i: int) -> F: ...
    @overload
    def __getitem__(self, i: slice) -> list[F]: ...
    def __getitem__(self, i: int | slice) -> F | list[F]:
        if isinstance(i, slice):
            return [self._make(j) for j in range(*i.indices(self._count))]
        try:
            i = operator.index(i)
        except TypeError:
            raise TypeError(
                f"{self._name()} indices must be integers or slices, not {type(i).__name__}"
            ) from None
        if i < 0:
            i += self._count
        if not 0 <= i < self._count:
            raise IndexError(f"{self._name()} index {i} out of range ({self._count} entries)")
        return self._make(i)

    def __iter__(self) -> Iterator[F]:
        for i in range(self._count):
            yield self._make(i)

    def frames(self) -> Iterator[F]:
        """The good frames only (no discard events)."""
        return (f for f in self if f.error is None)

    def errors(self) -> Iterator[F]:
        """The discard events only."""
        return (f for f in self if f.error is not None)

    def __repr__(self) -> str:
        return f"<{self._name()} of {self._count} entries>"


class FrameList(LazyFrames[Frame]):
    """A lazy sequence of the frames parse_stream found.

    Backed by compact arrays (offset, length, kind, error, start, end per
    entry); ``len()`` is immediate and Frame objects are built only when an
    item is read.  Subclasses provide ``_entry(i)``.
    """

    def _name(self) -> str:
        return FrameList.__name__

    def _entry(self, i: int) -> tuple[int, int, int, int, int | None, int | None]:
        raise NotImplementedError

    def _make(self, i: int) -> Frame:
        offset, length, kind, error, start, end = self._entry(i)
        return make_frame(
            kind,
            bytes(self._data[offset : offset + length]),
            offset,
            None if start is None else start / 1e6,
            None if end is None else end / 1e6,
            error,
        )
