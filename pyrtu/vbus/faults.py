"""Seeded, reproducible fault injection for the virtual bus.

`Faults` is the configuration (immutable); `TxFaults` is the per-drop state that
applies it to the bytes one drop transmits.  Every random decision comes from one
`random.Random` per drop, seeded from ``(seed, drop index)`` and consumed once per
transmitted byte in order, so the same seed and the same bytes give the same faults,
whatever the timing of the run.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

__all__ = ["FaultCounters", "Faults", "TxFaults", "collision_byte"]


@dataclass(frozen=True)
class Faults:
    """Faults to inject on a drop (or on every drop, when given to the bus globally).

    Line faults act on the bytes the drop *transmits*, so every receiver (and the
    capture) sees the same damaged stream:

    * ``bit_flip_rate``: probability that a data bit is inverted (per bit).
    * ``drop_rate``: probability that a byte is lost (its character slot stays
      silent; the following bytes keep their timing).
    * ``insert_rate``: probability that a random extra byte follows a byte (it takes
      its own character slot, delaying the rest of the frame by one character).
    * ``gap_every`` / ``gap_rate`` / ``gap_s``: a silence of ``gap_s`` seconds is
      inserted before every ``gap_every``-th transmitted byte and/or, at random,
      before a byte with probability ``gap_rate`` (to exercise t1.5 and t3.5).

    Adapter fault, acting on the bytes the drop *receives*:

    * ``batch_s`` / ``batch_bytes``: split delivery as USB adapters (FTDI latency
      timer) do it: received bytes are held and released in one burst ``batch_s``
      after the first of them arrived, or as soon as ``batch_bytes`` are held.

    ``seed`` seeds the random decisions (one generator per drop, derived from the
    seed and the drop index).  Unplugging a drop mid-frame is an action, not a rate:
    see `VirtualBus.unplug` (or ``unplug_after`` here, counted from bus start).
    """

    seed: int = 0
    bit_flip_rate: float = 0.0
    drop_rate: float = 0.0
    insert_rate: float = 0.0
    gap_every: int = 0
    gap_rate: float = 0.0
    gap_s: float = 0.0
    batch_s: float = 0.0
    batch_bytes: int = 62
    unplug_after: int | None = None

    def __post_init__(self) -> None:
        for name in ("bit_flip_rate", "drop_rate", "insert_rate", "gap_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be within [0, 1], got {value!r}")
        if self.gap_every < 0:
            raise ValueError("gap_every must be >= 0")
        if self.gap_s < 0 or self.batch_s < 0:
            raise ValueError("gap_s and batch_s must be >= 0")
        if (self.gap_every or self.gap_rate) and self.gap_s <= 0:
            raise ValueError("gap_every/gap_rate need gap_s > 0")
        if self.batch_bytes < 1:
            raise ValueError("batch_bytes must be >= 1")
        if self.unplug_after is not None and self.unplug_after < 0:
            raise ValueError("unplug_after must be >= 0")

    @property
    def line_faults(self) -> bool:
        """True when any fault acts on transmitted bytes."""
        return bool(
            self.bit_flip_rate
            or self.drop_rate
            or self.insert_rate
            or (self.gap_s and (self.gap_every or self.gap_rate))
        )


@dataclass
class FaultCounters:
    """Faults injected so far, by kind."""

    bit_flips: int = 0
    dropped: int = 0
    inserted: int = 0
    gaps: int = 0
    batches: int = 0
    unplugs: int = 0


def collision_byte(byte: int, other: int) -> int:
    """What receivers see for `byte` when `other` was on the wire at the same time.

    The two characters are XOR-ed; when that would leave `byte` unchanged (`other`
    is 0x00) the byte is inverted instead, so a collided byte always differs.
    """
    return byte ^ (other or 0xFF)


@dataclass
class TxFaults:
    """Per-drop state applying the line faults of a `Faults` to transmitted bytes."""

    faults: Faults
    drop: int
    counters: FaultCounters = field(default_factory=FaultCounters)
    count: int = 0
    _rng: random.Random = field(init=False, repr=False)
    _skip: int = field(init=False, repr=False)
    _log_keep: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(f"pyrtu.vbus:{self.faults.seed}:{self.drop}")
        p = self.faults.bit_flip_rate
        self._log_keep = math.log1p(-p) if 0.0 < p < 1.0 else 0.0
        self._skip = self._next_skip()

    def _next_skip(self) -> int:
        """Number of intact bits before the next flipped one (geometric law)."""
        p = self.faults.bit_flip_rate
        if p <= 0.0:
            return -1
        if p >= 1.0:
            return 0
        return int(math.log1p(-self._rng.random()) / self._log_keep)

    def _flip(self, byte: int) -> int:
        if self._skip < 0:
            return byte
        pos = 0
        while self._skip < 8 - pos:
            pos += self._skip
            byte ^= 1 << pos
            self.counters.bit_flips += 1
            pos += 1
            self._skip = self._next_skip()
        self._skip -= 8 - pos
        return byte

    def apply(self, byte: int) -> tuple[float, list[int | None]]:
        """Apply the faults to one transmitted byte.

        Returns ``(gap_s, slots)``: a silence to leave before the byte, then the
        character slots it occupies on the wire (``None`` is a slot whose byte was
        lost).  The random generator is consumed in a fixed order per byte.
        """
        f = self.faults
        rng = self._rng
        self.count += 1
        gap = 0.0
        if f.gap_s:
            if f.gap_every and self.count % f.gap_every == 0:
                gap = f.gap_s
            if f.gap_rate and rng.random() < f.gap_rate:
                gap = f.gap_s
            if gap:
                self.counters.gaps += 1
        byte = self._flip(byte)
        slot: int | None = byte
        if f.drop_rate and rng.random() < f.drop_rate:
            slot = None
            self.counters.dropped += 1
        slots = [slot]
        if f.insert_rate and rng.random() < f.insert_rate:
            slots.append(rng.randrange(256))
            self.counters.inserted += 1
        return gap, slots
