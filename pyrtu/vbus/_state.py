"""Hub state: counters and per-drop state; character-format helpers."""

from __future__ import annotations

import fcntl
import struct
import termios
from dataclasses import dataclass, field

from ._os import Pty
from .faults import FaultCounters, Faults, TxFaults

__all__ = [
    "BusCounters",
    "DropCounters",
    "DropState",
    "normalize_parity",
    "pending_input",
]


def pending_input(fd: int) -> int:
    """Bytes a client wrote that the hub has not read yet."""
    try:
        buf = fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0")
    except OSError:
        return 0
    return int(struct.unpack("i", buf)[0])


def normalize_parity(parity: str) -> str:
    p = parity.upper()[:1]
    if p not in ("N", "E", "O", "M", "S"):
        raise ValueError(f"parity must be N, E or O, got {parity!r}")
    return p


@dataclass
class DropCounters:
    """Per-drop counters (a snapshot when returned by `VirtualBus.counters`)."""

    tx_bytes: int = 0  #: bytes the client wrote that went on the wire
    rx_bytes: int = 0  #: bytes delivered to the client (echo included)
    collided_bytes: int = 0  #: own bytes corrupted by a collision
    collisions: int = 0  #: collisions this drop took part in
    overruns: int = 0  #: bytes lost because the client did not read (pty full)
    unheard: int = 0  #: bytes not delivered because no client had the drop open
    faults: FaultCounters = field(default_factory=FaultCounters)
    unplugged: bool = False


@dataclass(frozen=True)
class BusCounters:
    """Bus-wide counters: `wire_bytes` characters carried, `collisions` events."""

    wire_bytes: int
    collisions: int
    collided_bytes: int
    faults: dict[str, int]
    drops: tuple[DropCounters, ...]


class DropState:
    """What the hub keeps of a drop besides the schedule's state: its pty, link,
    clients, counters and fault configuration."""

    def __init__(self, index: int, echo: bool) -> None:
        self.index = index
        self.echo = echo
        self.pty: Pty | None = None
        self.link: str | None = None
        self.clients = 0
        self.watched = False
        self.counters = DropCounters()
        self.tx: TxFaults | None = None
        self.batch_ns = 0
        self.batch_bytes = 62

    @property
    def heard(self) -> bool:
        """Someone has the drop open (or opens are not tracked)."""
        return not (self.watched and self.clients == 0)

    def set_faults(self, faults: Faults | None) -> None:
        counters = self.counters.faults
        self.tx = None
        self.batch_ns = 0
        if faults is None:
            return
        if faults.line_faults:
            self.tx = TxFaults(faults, self.index, counters)
        self.batch_ns = round(faults.batch_s * 1e9)
        self.batch_bytes = faults.batch_bytes
