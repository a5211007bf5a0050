"""What has been handed to the broker and what it has acknowledged (sans-I/O).

Records are published in sequence order, at most ``window`` of them awaiting the
broker's acknowledgement.  `DeliveryWindow.sent` records a publication (its seq, the
client's message id, the time the value was read); `DeliveryWindow.acked` one
acknowledgement, which may come for any message id; `DeliveryWindow.contiguous` is then the
highest seq up to which every publication has been acknowledged: what the outbox
may forget.  `reset` forgets the publications in flight (the connection ended):
they are published again from the outbox, with the same sequence numbers.
A publication keeps its record until acknowledged (`record`: what to set aside
when the broker refuses it).  `DeliveryWindow.skipped` records a record passed by
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
    record: bytes = b""


class DeliveryWindow:
    """Publications awaiting acknowledgement (see the module docstring)."""

    def __init__(self, window: int) -> None:
        self.window = window
        self._order: deque[_Sent] = deque()
        self._by_mid: dict[int, _Sent] = {}
        self.contiguous: int | None = None
        self.latencies: deque[float] = deque(maxlen=4096)
        self.published = 0
        self.acknowledged = 0

    def __len__(self) -> int:
        return len(self._order)

    @property
    def full(self) -> bool:
        return len(self._order) >= self.window

    def sent(self, seq: int, mid: int, read_at: float, record: bytes = b"") -> None:
        s = _Sent(seq, read_at, False, record)
        self._order.append(s)
        self._by_mid[mid] = s
        self.published += 1

    def record(self, mid: int) -> tuple[int, bytes] | None:
        """(seq, record) of a publication awaiting its acknowledgement (None: no
        record's, such as a status)."""
        s = self._by_mid.get(mid)
        return None if s is None else (s.seq, s.record)

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
        s.record = b""
        self.acknowledged += 1
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
