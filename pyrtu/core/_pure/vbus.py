"""The virtual bus's wire as a sans-I/O schedule: the twin of csrc/rtu_vbus.c.

A half-duplex line ([SL] 3.3.1): each drop's queue holds ``(start_ns, byte)``
character slots one character time apart; a character is delivered to the receivers
when its last bit is sent; one that overlaps another drop's character collides and
is delivered corrupted.  Input: `Schedule.transmit` (what a drop wrote, and when);
output: `Schedule.take_output` after `Schedule.service`, and `Schedule.deadline`
(when to call it next).  Times are integer nanoseconds.  Every step is in the order
of the C file, and the queues and buffers have its bounds.

Two things only this twin does, for the Python loop of `pyrtu.vbus.VirtualBus`:
the capture (`capture`: every character on the wire with its time) and the seeded
line faults (`set_tx_faults`: `pyrtu.vbus.faults.TxFaults`, a `random.Random` per
drop), which is why the bus runs its Python loop when either is asked for.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

__all__ = ["MAX_CHAR_NS", "MAX_DROPS", "MAX_LEAD_NS", "OUT", "QUEUE", "Schedule", "VDrop"]

MAX_DROPS = 248  #: RTU_VBUS_MAX_DROPS: 247 slaves and a master ([SL] 2.2)
QUEUE = 4096  #: RTU_VBUS_QUEUE: character slots queued per drop
OUT = 4096  #: RTU_VBUS_OUT: bytes held or waiting to be written per drop
MAX_CHAR_NS = 1_000_000_000
MAX_LEAD_NS = 10_000_000
_TIME_LIMIT = 1 << 62
_MAX_BATCH_NS = 3600 * 1_000_000_000

COUNTERS = (
    "tx_bytes",
    "rx_bytes",
    "collided_bytes",
    "collisions",
    "overruns",
    "unheard",
    "batches",
)


class CaptureSink(Protocol):
    def add(self, drop: int, start_ns: int, byte: int, collision: bool) -> None: ...
    def end_run(self, drop: int) -> None: ...
    def pending(self) -> list[int]: ...


class TxFaultsLike(Protocol):
    def apply(self, byte: int) -> tuple[float, list[int | None]]: ...


def _time(t: int, name: str) -> int:
    if isinstance(t, bool) or not isinstance(t, int):
        raise TypeError(f"{name} must be an integer (ns), not {type(t).__name__}")
    if not -_TIME_LIMIT <= t <= _TIME_LIMIT:
        raise ValueError(f"{name} must be within +-2**62 ns, not {t!r}")
    return t


class VDrop:
    """One drop's state (the fields of rtu_vbus_drop)."""

    def __init__(self) -> None:
        self.q: deque[tuple[int, int]] = deque()
        self.tx_free = 0
        self.rx_end = 0
        self.last: tuple[int, int] | None = None
        self.alive = False
        self.cut = True
        self.echo = False
        self.due = False
        self.unplug_left = -1
        self.event_at: int | None = None
        self.batch_ns = 0
        self.batch_bytes = 62
        self.hold = bytearray()
        self.hold_deadline: int | None = None
        self.hold_end = 0
        self.out = bytearray()
        self.episode = -1
        self.tx: TxFaultsLike | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)

    def reset(self) -> None:
        self.q.clear()
        self.last = None
        self.hold.clear()
        self.hold_deadline = None
        self.out.clear()
        self.unplug_left = -1
        self.event_at = None
        self.due = False


class Schedule:
    """The wire shared by `ndrops` drops (rtu_vbus); every drop starts unplugged."""

    def __init__(self, ndrops: int, char_ns: int, lead_ns: int) -> None:
        for name, v in (("ndrops", ndrops), ("char_ns", char_ns), ("lead_ns", lead_ns)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"{name} must be an integer, not {type(v).__name__}")
        if not 1 <= ndrops <= MAX_DROPS:
            raise ValueError(f"ndrops must be 1..{MAX_DROPS}, not {ndrops}")
        if not 1 <= char_ns <= MAX_CHAR_NS or not 0 <= lead_ns <= MAX_LEAD_NS:
            raise ValueError(f"char_ns must be 1..{MAX_CHAR_NS} and lead_ns 0..{MAX_LEAD_NS}")
        self.drops = [VDrop() for _ in range(ndrops)]
        self.char_ns = char_ns
        self.lead_ns = lead_ns
        self.wire_bytes = 0
        self.collisions = 0
        self.collided = 0
        self._coll_until = -1
        #: Python loop only: where every character on the wire goes, and the time 0
        self.capture: CaptureSink | None = None
        self.t0_ns = 0

    def _drop(self, i: int) -> VDrop:
        if isinstance(i, bool) or not isinstance(i, int):
            raise TypeError(f"drop must be an integer, not {type(i).__name__}")
        if not 0 <= i < len(self.drops):
            raise IndexError(f"no drop {i} on a {len(self.drops)}-drop bus")
        return self.drops[i]

    # -- configuration --------------------------------------------------------------

    def plug(self, i: int) -> None:
        d = self._drop(i)
        d.alive = True
        d.cut = False
        d.tx_free = 0

    def unplug(self, i: int) -> None:
        d = self._drop(i)
        d.alive = False
        d.cut = True
        d.reset()

    def set_echo(self, i: int, on: bool) -> None:
        self._drop(i).echo = bool(on)

    def set_batch(self, i: int, batch_ns: int, batch_bytes: int) -> None:
        d = self._drop(i)
        if not 0 <= batch_ns <= _MAX_BATCH_NS or not 1 <= batch_bytes <= OUT:
            raise ValueError(f"batch must be 0..1 h and 1..{OUT} bytes")
        d.batch_ns = batch_ns
        d.batch_bytes = batch_bytes

    def set_unplug_after(self, i: int, left: int | None) -> None:
        self._drop(i).unplug_left = -1 if left is None or left < 0 else left

    def set_tx_faults(self, i: int, tx: TxFaultsLike | None) -> None:
        """Python loop only: line faults applied to what the drop transmits."""
        self._drop(i).tx = tx

    def cut(self, i: int, at: int) -> None:
        """The drop transmits nothing more and goes away at `at`."""
        self._cut(self._drop(i), _time(at, "at"))

    @staticmethod
    def _cut(d: VDrop, t: int) -> None:
        d.unplug_left = -1
        d.cut = True
        if d.event_at is None or t < d.event_at:
            d.event_at = t

    def clear_hold(self, i: int) -> None:
        d = self._drop(i)
        d.hold.clear()
        d.hold_deadline = None

    def space(self, i: int) -> int:
        return QUEUE - len(self._drop(i).q)

    # -- transmit side ----------------------------------------------------------------

    def transmit(self, i: int, data: bytes, now: int) -> None:
        """Queue what a drop's client wrote at `now`: one character slot after the other."""
        d = self._drop(i)
        _time(now, "now")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be bytes-like, not {type(data).__name__}")
        if d.cut:
            return  # a drop going away sends nothing more
        if len(data) > QUEUE - len(d.q):
            raise BufferError(f"drop {i}: {len(data)} bytes for {QUEUE - len(d.q)} free slots")
        c = self.char_ns
        # Causality: the client may be answering the last byte it was given, so its
        # reply cannot start before that byte's end on the wire.
        t = max(now, d.tx_free, d.rx_end)
        if t > _TIME_LIMIT - (len(data) + 1) * c:
            raise ValueError("the wire would run past the clock's range")
        q = d.q
        tx = d.tx
        if tx is None and d.unplug_left < 0:  # the common case, in one pass
            q.extend(zip(range(t, t + len(data) * c, c), data, strict=True))
            d.counters["tx_bytes"] += len(data)
            d.tx_free = t + len(data) * c
            return
        for b in data:
            if d.unplug_left == 0:
                self._cut(d, t)
                break
            if tx is not None:
                gap, slots = tx.apply(b)
                if gap:
                    t += round(gap * 1e9)
            else:
                slots = [b]
            for v in slots:
                if v is not None:  # inserted bytes may go past QUEUE: bounded by the read
                    q.append((t, v))
                t += c
            d.counters["tx_bytes"] += 1
            if d.unplug_left > 0:
                d.unplug_left -= 1
                if d.unplug_left == 0:
                    self._cut(d, t)
                    break
        d.tx_free = t

    # -- receive side ------------------------------------------------------------------

    def deadline(self) -> int | None:
        """When `service` must run next (deliveries are due `lead` early)."""
        t: int | None = None
        c = self.char_ns
        for d in self.drops:
            if d.q and (t is None or d.q[0][0] + c < t):
                t = d.q[0][0] + c
            if d.hold_deadline is not None and (t is None or d.hold_deadline < t):
                t = d.hold_deadline
        if t is not None:
            t -= self.lead_ns
        for d in self.drops:
            if d.event_at is not None and (t is None or d.event_at < t):
                t = d.event_at
        return t

    def _overlap(self, src: VDrop, start: int) -> tuple[VDrop, int, int] | None:
        """Another drop's character on the wire during [start, start + char)."""
        c = self.char_ns
        for o in self.drops:
            if o is src:
                continue
            if o.last is not None and start - c < o.last[0] < start + c:
                return o, o.last[0], o.last[1]
            if o.q and start - c < o.q[0][0] < start + c:
                return o, o.q[0][0], o.q[0][1]
        return None

    @staticmethod
    def _out_add(r: VDrop, data: bytes | bytearray) -> None:
        k = min(len(data), OUT - len(r.out))
        r.out += data[:k]
        r.counters["overruns"] += len(data) - k

    def _release(self, r: VDrop) -> None:
        self._out_add(r, r.hold)
        r.rx_end = r.hold_end
        r.hold.clear()
        r.hold_deadline = None
        r.counters["batches"] += 1

    def service(self, now: int) -> list[int]:
        """Deliver every character whose last bit is sent by `now` + lead into the
        output buffers; return the drops whose unplug time has come."""
        _time(now, "now")
        drops = self.drops
        cap = self.capture
        c = self.char_ns
        horizon = now + self.lead_ns  # wire time reached by what is written now
        touched = False
        while True:
            src: VDrop | None = None
            first = 0
            for d in drops:  # the queued character that ends first
                if d.q and (src is None or d.q[0][0] < first):
                    src, first = d, d.q[0][0]
            if src is None or first + c > horizon:
                break
            start, value = src.q.popleft()
            end = start + c
            src.last = (start, value)
            hit = self._overlap(src, start)
            if hit is not None:
                other, other_start, other_byte = hit
                # XOR, or the inverted byte when the other is 0x00 (collision_byte)
                value ^= other_byte or 0xFF
                self.collided += 1
                src.counters["collided_bytes"] += 1
                if start >= self._coll_until:
                    self.collisions += 1
                self._coll_until = max(self._coll_until, end, other_start + c)
                for x in (src, other):
                    if x.episode != self.collisions:
                        x.episode = self.collisions
                        x.counters["collisions"] += 1
            self.wire_bytes += 1
            if cap is not None:
                cap.add(drops.index(src), start - self.t0_ns, value, hit is not None)
                touched = True
            for r in drops:
                if not r.alive or (r is src and not r.echo):
                    continue
                if r.batch_ns:
                    if r.hold_deadline is not None and r.hold_deadline < end:
                        self._release(r)  # due before this byte arrived (the hub ran late)
                    if not r.hold:
                        r.hold_deadline = end + r.batch_ns
                    r.hold.append(value)
                    r.hold_end = end
                    if len(r.hold) >= r.batch_bytes:
                        self._release(r)
                else:
                    if len(r.out) < OUT:
                        r.out.append(value)
                    else:
                        r.counters["overruns"] += 1
                    r.rx_end = end
        if touched and cap is not None:
            for i in cap.pending():
                if not drops[i].q:
                    cap.end_run(i)
        due: list[int] = []
        for i, r in enumerate(drops):
            if r.hold_deadline is not None and r.hold_deadline <= horizon:
                self._release(r)
            if r.event_at is not None and r.event_at <= now:
                r.event_at = None
                due.append(i)
        return due

    def take_output(self, i: int) -> bytes:
        """What the drop receives now (call `written` once it is written)."""
        return bytes(self._drop(i).out)

    def written(self, i: int, n: int, heard: int) -> None:
        """`n` of the output's bytes were written (the rest are overruns); heard 0:
        nobody had the drop open (all unheard); heard < 0: no pty (discarded)."""
        d = self._drop(i)
        if not 0 <= n <= len(d.out):
            raise ValueError(f"written: n must be 0..{len(d.out)}, not {n}")
        if heard > 0:
            d.counters["rx_bytes"] += n
            d.counters["overruns"] += len(d.out) - n
        elif heard == 0:
            d.counters["unheard"] += len(d.out)
        d.out.clear()

    def busy(self) -> bool:
        """Something is queued, held or pending on the wire."""
        return any(d.event_at is not None or d.q or d.hold or d.out for d in self.drops)

    def drop_counters(self, i: int) -> dict[str, int]:
        return dict(self._drop(i).counters)

    def alive(self, i: int) -> bool:
        return self._drop(i).alive

    def held(self, i: int) -> bytes:
        """What the drop's batch fault holds back."""
        return bytes(self._drop(i).hold)

    def queued(self, i: int) -> list[tuple[int, int]]:
        """The drop's queued character slots (start, byte)."""
        return list(self._drop(i).q)
