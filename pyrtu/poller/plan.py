"""Coalescing: points into blocks, one read request each, as pure functions.

`Wire` prices a transaction in seconds of bus time: the inter-frame silence
(t3.5), the request and the response frames (characters x character time) and the
slave's turnaround.  A Modbus TCP bus (``tcp://``, `Wire.tcp`) has no character
time and no silence: a transaction costs its round trip, `TCP_ROUND_TRIP` until
the slave's own is measured (the measured turnaround is then the whole of it).
`plan` groups the points of one slave and table into blocks:

* a block never exceeds the device's maximum per request (`Limits`: 125 registers
  and 2000 bits by the spec; less where a device says so, e.g. the Bonfiglioli's
  one register per FC 03, or a maximum ADU size such as the WEG drives' 64 bytes);
* a block never crosses a learned *cut* (an address where a read of a wider block
  answered exception 2: a hole in the map);
* two neighbours are merged when the merged request costs no more wire time per
  second than the two separate ones::

      wire(merged) / min(I_a, I_b)  <=  wire(a) / I_a + wire(b) / I_b

  For equal intervals that is "read the gap when reading it is cheaper than the
  overhead of a second request"; for different intervals the slower points ride
  along with the faster ones only when that is cheaper.  ``max_gap`` (in
  registers, or bits) additionally bounds the gap when it is set.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from .points import Point

#: Application Protocol V1.1b 6.1-6.4: per-request maxima
SPEC_MAX_REGISTERS = 125
SPEC_MAX_BITS = 2000
#: the read functions of the four tables
FUNCTIONS = {"coils": 1, "discrete_inputs": 2, "holding": 3, "input": 4}


@dataclass(frozen=True, slots=True)
class Limits:
    """A device's limits per request (None: the spec's) and the merge bound."""

    max_registers: int | None = None
    max_bits: int | None = None
    max_adu: int | None = None
    max_gap: int | None = None

    def __post_init__(self) -> None:
        for name, lo, hi in (
            ("max_registers", 1, SPEC_MAX_REGISTERS),
            ("max_bits", 1, SPEC_MAX_BITS),
            ("max_adu", 6, 256),
            ("max_gap", 0, 0xFFFF),
        ):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{name}: must be an integer {lo}..{hi}, not {v!r}")

    def registers(self) -> int:
        """Registers per read: the least of the spec's, ``max_registers`` and what fits
        a response of ``max_adu`` bytes (slave, function, count, 2n, CRC)."""
        n = SPEC_MAX_REGISTERS if self.max_registers is None else self.max_registers
        if self.max_adu is not None:
            n = min(n, (self.max_adu - 5) // 2)
        return max(n, 1)

    def bit_count(self) -> int:
        n = SPEC_MAX_BITS if self.max_bits is None else self.max_bits
        if self.max_adu is not None:
            n = min(n, (self.max_adu - 5) * 8)
        return max(n, 1)

    def per_request(self, table: str) -> int:
        return self.bit_count() if table in ("coils", "discrete_inputs") else self.registers()


#: the round trip a Modbus TCP transaction is assumed to take until a slave's own is
#: measured: a device on the local network (a PLC answers in 1-5 ms)
TCP_ROUND_TRIP = 0.002


@dataclass(frozen=True, slots=True)
class Wire:
    """The time a transaction holds a bus: ``char`` seconds per character, ``t35``
    of silence before each request, ``turnaround`` from the end of the request to
    the first byte of the answer.  ``ascii``: two characters per byte plus the
    ``:`` LRC CR LF framing instead of the CRC."""

    char: float
    t35: float
    turnaround: float = 0.0
    ascii: bool = False

    @classmethod
    def tcp(cls, round_trip: float = TCP_ROUND_TRIP) -> Wire:
        """The model of a Modbus TCP connection: no character time (a frame of 260
        bytes is 21 us at 100 Mbit/s), no t3.5; a transaction holds the connection
        for its round trip (``turnaround``: from the request sent to the answer
        received), the poller keeping one transaction in flight per bus."""
        return cls(0.0, 0.0, turnaround=round_trip)

    def chars(self, adu_bytes: int) -> int:
        """Characters on the wire for an RTU ADU of ``adu_bytes`` (CRC included)."""
        if self.ascii:
            return 1 + 2 * (adu_bytes - 2 + 1) + 2
        return adu_bytes

    def frames(self, request: int, response: int, turnaround: float | None = None) -> float:
        """Seconds for a request of ``request`` bytes answered by ``response`` bytes
        (RTU ADU sizes); ``response`` 0: no answer (broadcast)."""
        ta = self.turnaround if turnaround is None else turnaround
        t = self.t35 + self.chars(request) * self.char
        if response:
            t += ta + self.chars(response) * self.char
        return t

    def read(self, table: str, count: int, turnaround: float | None = None) -> float:
        """Seconds for a read of ``count`` registers (or bits) of ``table``."""
        return self.frames(8, response_size(table, count), turnaround)


def response_size(table: str, count: int) -> int:
    """The RTU ADU size of a read response: slave, function, byte count, data, CRC."""
    data = (count + 7) // 8 if table in ("coils", "discrete_inputs") else 2 * count
    return 5 + data


@dataclass(frozen=True, slots=True)
class Block:
    """One read request: ``count`` registers (or bits) of ``table`` at ``address``,
    covering ``points``; ``interval`` is the shortest of theirs."""

    bus: str
    slave: int
    table: str
    address: int
    count: int
    points: tuple[Point, ...]
    interval: float

    @property
    def function(self) -> int:
        return FUNCTIONS[self.table]

    @property
    def end(self) -> int:
        return self.address + self.count

    @property
    def key(self) -> tuple[str, int, str, int, int]:
        return (self.bus, self.slave, self.table, self.address, self.count)

    def __repr__(self) -> str:
        names = ",".join(p.name for p in self.points)
        return (
            f"Block(slave {self.slave} {self.table} {self.address}+{self.count} "
            f"every {self.interval:g} s: {names})"
        )


def _block(points: Sequence[Point]) -> Block:
    first = points[0]
    start = min(p.address for p in points)
    end = max(p.end for p in points)
    return Block(
        first.bus,
        first.slave,
        first.table,
        start,
        end - start,
        tuple(points),
        min(p.interval for p in points),
    )


def merge_pays(wire: Wire, a: Block, b: Block) -> bool:
    """Whether reading ``a`` and ``b`` as one block costs no more wire time per
    second than reading them apart (the rule in the module docstring)."""
    start, end = min(a.address, b.address), max(a.end, b.end)
    merged = wire.read(a.table, end - start) / min(a.interval, b.interval)
    apart = wire.read(a.table, a.count) / a.interval + wire.read(b.table, b.count) / b.interval
    return merged <= apart * (1 + 1e-9)


#: how often a cut may be withdrawn before it is kept for good (a bound on learning)
MAX_WITHDRAWALS = 8

_Key = tuple[str, int, str]


@dataclass
class Cuts:
    """Learned boundaries: ``cuts[(bus, slave, table)]`` holds addresses no block
    may read across (a block may end before one or start at one).

    A cut learned from a block ``lo..hi-1`` that answered exception 2 is *proven*
    when the block had one gap (two runs of points: the hole is in that gap) and
    *suspected* otherwise (the cut went at the widest gap, the hole may be in
    another).  `learn` withdraws a suspected cut when a later exception 2 puts a
    cut after a gap inside the block it came from (that hole alone may explain the
    first answer), and `forget_point` withdraws every cut whose block held a point that
    turned out not to exist; the planner then reads across a withdrawn cut again,
    and a read that fails puts it back as proven or suspected.  So the cuts
    converge to the ones the holes need: the fewest requests.  A cut withdrawn
    `MAX_WITHDRAWALS` times is kept for good."""

    cuts: dict[_Key, set[int]] = field(default_factory=dict)
    #: where each cut came from: (lo, hi) of the failing block, proven
    origin: dict[tuple[_Key, int], tuple[int, int, bool]] = field(default_factory=dict)
    withdrawn: dict[tuple[_Key, int], int] = field(default_factory=dict)

    def add(self, bus: str, slave: int, table: str, address: int) -> None:
        """A cut known for certain (kept for good)."""
        key = (bus, slave, table)
        self.cuts.setdefault(key, set()).add(address)
        self.origin.pop((key, address), None)
        self.withdrawn[(key, address)] = MAX_WITHDRAWALS

    def learn(self, block: Block, cut: int, proven: bool) -> list[int]:
        """Exception 2 on ``block``, split at ``cut``: add the cut and withdraw the
        suspected cuts whose blocks held the gap before this one.  Returns the
        withdrawn addresses."""
        key = (block.bus, block.slave, block.table)
        gap = max((p.end for p in block.points if p.address < cut), default=block.address)
        out = [
            c
            for c in self.cuts.get(key, ())
            if c != cut
            and (o := self.origin.get((key, c))) is not None
            and not o[2]
            and o[0] <= gap
            and cut < o[1]
        ]
        for c in out:
            self._withdraw(key, c)
        self.cuts.setdefault(key, set()).add(cut)
        if (key, cut) not in self.origin or proven:
            self.origin[(key, cut)] = (block.address, block.end, proven)
        return out

    def forget_point(self, bus: str, slave: int, table: str, address: int) -> list[int]:
        """A point at ``address`` does not exist: withdraw the cuts learned from
        blocks that held it.  Returns the withdrawn addresses."""
        key = (bus, slave, table)
        out = [
            c
            for c in self.cuts.get(key, ())
            if (o := self.origin.get((key, c))) is not None and o[0] <= address < o[1]
        ]
        for c in out:
            self._withdraw(key, c)
        return out

    def _withdraw(self, key: _Key, cut: int) -> None:
        n = self.withdrawn.get((key, cut), 0)
        if n >= MAX_WITHDRAWALS:
            self.origin.pop((key, cut), None)
            return
        self.withdrawn[(key, cut)] = n + 1
        self.cuts[key].discard(cut)
        del self.origin[(key, cut)]

    def between(self, bus: str, slave: int, table: str, lo: int, hi: int) -> bool:
        """Whether a cut lies in ``lo < cut < hi``... i.e. a block ``lo..hi-1`` would
        cross one."""
        return any(lo < c < hi for c in self.cuts.get((bus, slave, table), ()))


def plan(
    points: Iterable[Point],
    wire: Wire,
    limits: Limits | None = None,
    cuts: Cuts | None = None,
) -> list[Block]:
    """The blocks for ``points`` (any mix of slaves and tables: grouped by bus,
    slave and table), sorted by (bus, slave, table, address).

    Points are taken in address order; each joins the block before it when the
    block stays within the device's maximum, crosses no learned cut, the gap is at
    most ``limits.max_gap`` (when set) and `merge_pays`.  A point wider than the
    maximum (a long string) is a block of its own.
    """
    groups: dict[tuple[str, int, str], list[Point]] = {}
    for p in points:
        groups.setdefault((p.bus, p.slave, p.table), []).append(p)
    cuts = cuts or Cuts()
    limits = limits or Limits()
    out: list[Block] = []
    for (bus, slave, table), members in sorted(groups.items()):
        limit = limits.per_request(table)
        members.sort(key=lambda p: (p.address, p.size, p.name))
        current: list[Point] = []
        block: Block | None = None
        for p in members:
            if block is None:
                current, block = [p], _block([p])
                continue
            single = _block([p])
            start, end = block.address, max(block.end, p.end)
            gap = p.address - block.end
            fits = (
                end - start <= limit
                and not cuts.between(bus, slave, table, start, end)
                and (limits.max_gap is None or gap <= limits.max_gap)
                and (gap <= 0 or merge_pays(wire, block, single))
            )
            if fits:
                current.append(p)
                block = _block(current)
            else:
                out.append(block)
                current, block = [p], single
        if block is not None:
            out.append(block)
    return out


def split(block: Block) -> tuple[Block, Block] | None:
    """A block that answered exception 2, in two at a point boundary, or None when
    it is one point (or points sharing one start address) and cannot be split.

    The cut goes where the hole most likely is: the widest gap between points
    (the points themselves are presumed to exist); contiguous points are halved.
    """
    pts = sorted(block.points, key=lambda p: (p.address, p.end))
    starts = sorted({p.address for p in pts})
    if len(starts) < 2:
        return None
    best, cut = -1, starts[len(starts) // 2]
    reach = pts[0].end
    for p in pts[1:]:
        if p.address >= reach and p.address - reach > best and p.address > pts[0].address:
            best, cut = p.address - reach, p.address
        reach = max(reach, p.end)
    if best <= 0:
        cut = starts[len(starts) // 2]
    lo = [p for p in block.points if p.address < cut]
    hi = [p for p in block.points if p.address >= cut]
    return _block(lo), _block(hi)


def gaps(block: Block) -> int:
    """How many gaps (addresses read but not a point's) ``block`` has between its
    points: with one, a hole that made it answer exception 2 is in that gap."""
    pts = sorted(block.points, key=lambda p: (p.address, p.end))
    n, reach = 0, pts[0].end
    for p in pts[1:]:
        n += p.address > reach
        reach = max(reach, p.end)
    return n


def chunks(table: str, address: int, count: int, limits: Limits) -> list[tuple[int, int]]:
    """``(address, count)`` reads covering ``count`` registers (or bits) within the
    device's maximum per request (for on-demand reads)."""
    step = limits.per_request(table)
    return [(a, min(step, address + count - a)) for a in range(address, address + count, step)]


__all__ = [
    "FUNCTIONS",
    "SPEC_MAX_BITS",
    "SPEC_MAX_REGISTERS",
    "TCP_ROUND_TRIP",
    "Block",
    "Cuts",
    "Limits",
    "Wire",
    "chunks",
    "gaps",
    "merge_pays",
    "plan",
    "response_size",
    "split",
]
