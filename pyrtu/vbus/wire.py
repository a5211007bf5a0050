"""The wire: a time-driven scheduler of the characters the drops transmit.

Each drop's queue holds ``(start_ns, byte)`` slots one character time apart (on
the `time.perf_counter_ns` clock).  A character is delivered to the receivers when
its last bit is sent; a character that overlaps another drop's character in time
collides and is delivered corrupted.  The hub thread calls `Wire.transmit` with
what clients wrote, `Wire.service` when `Wire.deadline` comes, and holds the lock.
"""

from __future__ import annotations

import os

from ._state import DropState
from .capture import CaptureWriter
from .faults import collision_byte

__all__ = ["Wire"]


class Wire:
    """The half-duplex wire shared by the drops, and its counters."""

    def __init__(self, drops: list[DropState], char_ns: int, lead_ns: int) -> None:
        self.drops = drops
        self.char_ns = char_ns
        #: deliveries are written this early (compensates pty latency to the client)
        self.lead_ns = lead_ns
        self.capture: CaptureWriter | None = None
        self.t0_ns = 0
        self.events: list[tuple[int, int]] = []  # (time, drop): unplug events
        self.wire_bytes = 0
        self.collisions = 0
        self.collided = 0
        self._coll_until = -1

    def busy(self) -> bool:
        """Something is queued, held, or pending on the wire."""
        return bool(self.events) or any(d.txq or d.hold or d.out for d in self.drops)

    def deadline(self) -> int | None:
        """When the hub must run next (deliveries are written `lead` early)."""
        t: int | None = None
        for d in self.drops:
            if d.txq and (t is None or d.txq[0][0] + self.char_ns < t):
                t = d.txq[0][0] + self.char_ns
            if d.hold_deadline is not None and (t is None or d.hold_deadline < t):
                t = d.hold_deadline
        if t is not None:
            t -= self.lead_ns
        for when, _ in self.events:
            if t is None or when < t:
                t = when
        return t

    # -- transmit side -------------------------------------------------------------

    def transmit(self, d: DropState, data: bytes, now: int) -> None:
        """Queue what a client wrote: one character slot after the other."""
        if d.cut:
            return
        c = self.char_ns
        # Causality: the client may be answering the last byte it was given, so
        # its reply cannot start before that byte's end on the wire (the latency
        # compensation would otherwise let it start early and collide).
        t = max(now, d.tx_free, d.rx_end)
        q = d.txq
        tx = d.tx
        if tx is None and d.unplug_left is None:
            for b in data:
                q.append((t, b))
                t += c
            d.counters.tx_bytes += len(data)
            d.tx_free = t
            return
        for b in data:
            if d.unplug_left == 0:
                self.cut(d, t)
                break
            if tx is not None:
                gap, slots = tx.apply(b)
                if gap:
                    t += round(gap * 1e9)
            else:
                slots = [b]
            for v in slots:
                if v is not None:
                    q.append((t, v))
                t += c
            d.counters.tx_bytes += 1
            if d.unplug_left is not None:
                d.unplug_left -= 1
                if d.unplug_left <= 0:
                    self.cut(d, t)
                    break
        d.tx_free = t

    def cut(self, d: DropState, t: int) -> None:
        """The drop transmits nothing more and goes away at `t`."""
        d.unplug_left = None
        d.cut = True
        self.events.append((t, d.index))

    def overlap(self, src: DropState, start: int) -> tuple[DropState, int, int] | None:
        """Another drop's character on the wire during [start, start + char)."""
        c = self.char_ns
        for o in self.drops:
            if o is src:
                continue
            if o.last is not None and start - c < o.last[0] < start + c:
                return o, o.last[0], o.last[1]
            if o.txq and start - c < o.txq[0][0] < start + c:
                return o, o.txq[0][0], o.txq[0][1]
        return None

    # -- receive side ---------------------------------------------------------------

    def service(self, now: int) -> list[int]:
        """Deliver every character whose last bit is sent by `now` (+ lead).

        Returns the drops whose unplug time has come.
        """
        drops = self.drops
        cap = self.capture
        c = self.char_ns
        horizon = now + self.lead_ns  # wire time reached by what is written now
        touched = False
        while True:
            src: DropState | None = None
            first = 0
            for d in drops:  # the queued character that ends first
                if d.txq and (src is None or d.txq[0][0] < first):
                    src, first = d, d.txq[0][0]
            if src is None or first + c > horizon:
                break
            start, byte = src.txq.popleft()
            end = start + c
            src.last = (start, byte)
            value = byte
            hit = self.overlap(src, start)
            if hit is not None:
                other, other_start, other_byte = hit
                value = collision_byte(byte, other_byte)
                self.collided += 1
                src.counters.collided_bytes += 1
                if start >= self._coll_until:
                    self.collisions += 1
                self._coll_until = max(self._coll_until, end, other_start + c)
                for x in (src, other):
                    if x.episode != self.collisions:
                        x.episode = self.collisions
                        x.counters.collisions += 1
            self.wire_bytes += 1
            if cap is not None:
                cap.add(src.index, start - self.t0_ns, value, hit is not None)
            for r in drops:
                if not r.alive or (r is src and not r.echo):
                    continue
                if r.batch_ns:
                    if r.hold_deadline is not None and r.hold_deadline < end:
                        self._release(r)  # due before this byte arrived (hub ran late)
                    if not r.hold:
                        r.hold_deadline = end + r.batch_ns
                    r.hold.append(value)
                    r.hold_end = end
                    if len(r.hold) >= r.batch_bytes:
                        self._release(r)
                else:
                    r.out.append(value)
                    r.rx_end = end
            touched = True
        for r in drops:
            if r.hold_deadline is not None and r.hold_deadline <= horizon:
                self._release(r)
            if r.out:
                self._write(r)
        if touched and cap is not None:
            for i in cap.pending():
                if not drops[i].txq:
                    cap.end_run(i)
        if not self.events:
            return []
        due = [i for t, i in self.events if t <= now]
        if due:
            self.events = [e for e in self.events if e[0] > now]
        return due

    def _release(self, r: DropState) -> None:
        r.out += r.hold
        r.rx_end = r.hold_end
        r.hold.clear()
        r.hold_deadline = None
        r.counters.faults.batches += 1

    def _write(self, r: DropState) -> None:
        data = bytes(r.out)
        r.out.clear()
        if r.pty is None:
            return
        if r.watched and r.clients == 0:
            r.counters.unheard += len(data)
            return
        try:
            n = os.write(r.pty.master, data)
        except BlockingIOError:
            n = 0
        except OSError:
            n = 0
        r.counters.rx_bytes += n
        r.counters.overruns += len(data) - n
