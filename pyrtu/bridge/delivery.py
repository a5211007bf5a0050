"""What has been handed to the broker and what it has acknowledged (sans-I/O).

Records are published in sequence order, at most ``window`` of them awaiting the
broker's acknowledgement.  `DeliveryWindow.sent` records a publication (its seq, the
client's message id, the time the value was read); `DeliveryWindow.acked` one
acknowledgement, which may come for any message id; `DeliveryWindow.contiguous` is then the
highest seq up to which every publication has been acknowledged: what the outbox
may forget.  `reset` forgets the publications in flight (the connection ended):
they are published again from the outbox, with the same sequence numbers.
A publication keeps its record until acknowledged (`records`: what to set aside
when the broker refuses it).  A device message (``messages = "device"``,
`DeliveryWindow.sent_group`) is one publication of several records, consecutive in
the outbox's order (what lies between them was set aside before it): its
acknowledgement acknowledges every one of them, so it stands in the order at
its last record's seq, and `contiguous` never passes a record of a message
awaiting its acknowledgement.  `DeliveryWindow.skipped` records a record passed by
unpublished (set aside: it never can be): it counts as acknowledged in its
place, neither holding `contiguous` back nor moving it past a publication still
in flight.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from ..poller.events import percentile


@dataclass(slots=True)
class _Sent:
    seq: int
    read_at: float  # Unix time the value was read off the wire (0: unknown)
    done: bool = False
    records: list[tuple[int, bytes]] | None = None  # (seq, record) of what it carries


class DeliveryWindow:
    """Publications awaiting acknowledgement (see the module docstring)."""

    def __init__(self, window: int) -> None:
        self.window = window
        self._order: deque[_Sent] = deque()
        self._by_mid: dict[int, _Sent] = {}
        self.contiguous: int | None = None
        self.latencies: deque[float] = deque(maxlen=4096)
        self.published = 0  # records handed to the client (a device message: each of them)
        self.acknowledged = 0  # records the broker acknowledged

    def __len__(self) -> int:
        return len(self._order)

    @property
    def full(self) -> bool:
        return len(self._order) >= self.window

    def sent(self, seq: int, mid: int, read_at: float, record: bytes = b"") -> None:
        """The publication ``mid`` of one record."""
        self.sent_group(mid, read_at, [(seq, record)])

    def sent_group(self, mid: int, read_at: float, records: list[tuple[int, bytes]]) -> None:
        """The publication ``mid`` of ``records`` (seq order, consecutive in the
        outbox's: see the module docstring), the first read at ``read_at``."""
        s = _Sent(records[-1][0], read_at, False, records)
        self._order.append(s)
        self._by_mid[mid] = s
        self.published += len(records)

    def records(self, mid: int) -> list[tuple[int, bytes]]:
        """(seq, record) of what a publication awaiting its acknowledgement carries
        (none: no record's, such as a status)."""
        s = self._by_mid.get(mid)
        return [] if s is None or s.records is None else s.records

    def skipped(self, seq: int) -> bool:
        """A record passed by, in its place in the order, as if acknowledged; True
        when `contiguous` moved."""
        self._order.append(_Sent(seq, 0.0, True))
        return self._advance()

    def acked(self, mid: int, now: float) -> bool:
        """An acknowledgement at ``now`` (Unix); True when `contiguous` moved."""
        s = self._by_mid.pop(mid, None)
        if s is None:
            return False  # not a point's record (status, result, stats)
        s.done = True
        self.acknowledged += len(s.records or ())
        s.records = None
        if s.read_at:
            self.latencies.append(now - s.read_at)
        return self._advance()

    def _advance(self) -> bool:
        moved = False
        order = self._order
        while order and order[0].done:
            self.contiguous = order.popleft().seq
            moved = True
        return moved

    def reset(self) -> None:
        self._order.clear()
        self._by_mid.clear()

    def latency(self, q: float) -> float | None:
        """Percentile ``q`` of read-to-acknowledgement times (seconds) lately."""
        return percentile(sorted(self.latencies), q)


__all__ = ["DeliveryWindow"]
