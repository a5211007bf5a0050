"""The slave's data: four sparse tables (and optional files) of address ranges.

::

    store = DataStore()
    store.holding_registers.add_range(0, [0] * 100)
    store.holding_registers.add_range(680, [0x0000], read_only=True)   # status word
    store.coils.add_range(0, [False] * 16, on_write=lambda addr, values: ...)

Semantics of a request (the behaviour the WEG and Bonfiglioli manuals give):

* an address outside every range: exception 2 (ILLEGAL DATA ADDRESS);
* a write to a read-only range, or a value a validator rejects: exception 3;
* a callback (``on_read``, ``on_write``) that raises: exception 4 (or the code
  of a `SlaveException` it raises);
* atomic: every address and value is checked before anything is stored, and
  the stored values are restored when an ``on_write`` callback fails.

A request may span adjacent ranges; each range applies its own rules.
``get``/``set`` are for the owner (a simulator): no read-only check, no
validator, no callback.  All access goes through the store's lock.

A store served by `pyrtu.tcp.server.TcpServer` on the C core also has an *image*
(`pyrtu.protocol._image.StoreImage`): a copy of its tables in C memory from which
the server's C engine answers plain reads without Python.  The changes made while
the store's lock is held reach the image in one step when its outermost holder
releases it, so a reader of the image sees all of them or none, as a reader
holding the lock would.
"""

from __future__ import annotations

import bisect
import itertools
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from pyrtu.pdu.errors import SlaveException

Value = int | bool
Validator = Callable[[int, Value], bool]
OnWrite = Callable[[int, list[Value]], object]
OnRead = Callable[[int, int], object]


@dataclass
class _Range:
    start: int
    values: list[Value]
    read_only: bool = False
    validator: Validator | None = None
    on_write: OnWrite | None = None
    on_read: OnRead | None = None
    end: int = field(init=False)

    def __post_init__(self) -> None:
        self.end = self.start + len(self.values)


# (range, first index inside it, number of values)
_Segment = tuple[_Range, int, int]


class Mirror(Protocol):
    """What the store's lock keeps current (`pyrtu.protocol._image.StoreImage`)."""

    def changed(self) -> bool:
        """Whether the tables changed since the last `update` (their versions)."""

    def update(self) -> None:
        """Copy the tables' changes (called with the store's lock held)."""


class StoreLock:
    """The store's lock: a `threading.RLock` (``with store.lock:``, re-entrant); with
    a `Mirror` attached, the outermost release first brings it up to date (one
    step for every change made under the lock)."""

    __slots__ = ("_depth", "_lock", "mirror")

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._depth = 0  # (only its holder changes it)
        self.mirror: Mirror | None = None

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        got = self._lock.acquire(blocking, timeout)
        if got:
            self._depth += 1
        return got

    def release(self) -> None:
        """RuntimeError when not held by this thread (as `threading.RLock`)."""
        lock = self._lock
        if not lock._is_owned():  # type: ignore[attr-defined]
            raise RuntimeError("cannot release un-acquired lock")
        self._depth -= 1
        try:
            if not self._depth and self.mirror is not None and self.mirror.changed():
                self.mirror.update()
        finally:
            lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class Table:
    """One table: a sparse map of address ranges, each with its own rules."""

    def __init__(self, name: str, bits: bool, lock: StoreLock, limit: int = 0xFFFF) -> None:
        self.name = name
        self.bits = bits
        self.limit = limit
        self._lock = lock
        self._ranges: list[_Range] = []
        self._starts: list[int] = []
        #: counts the changes to the values (a range added, `set`, `set_many`, `set_each`,
        #: a request's write, its undoing): while it stays the same, so do the values
        self.version = 0

    # ------------------------------------------------------------------- owner

    def _value(self, address: int, value: object) -> Value:
        if self.bits:
            if isinstance(value, bool) or (isinstance(value, int) and value in (0, 1)):
                return bool(value)
            raise ValueError(f"{self.name}[{address}]: a bit is a bool (or 0/1), not {value!r}")
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
            raise ValueError(f"{self.name}[{address}]: a register is 0..65535, not {value!r}")
        return value

    def add_range(
        self,
        address: int,
        values: Iterable[object],
        read_only: bool = False,
        validator: Validator | None = None,
        on_write: OnWrite | None = None,
        on_read: OnRead | None = None,
    ) -> None:
        """Serve ``values`` from ``address`` on; ranges may not overlap."""
        if (
            isinstance(address, bool)
            or not isinstance(address, int)
            or not 0 <= address <= self.limit
        ):
            raise ValueError(f"{self.name}: address must be 0..{self.limit}, not {address!r}")
        vals = [self._value(address + i, v) for i, v in enumerate(values)]
        if not vals:
            raise ValueError(f"{self.name}: a range needs at least one value")
        if address + len(vals) > self.limit + 1:
            raise ValueError(f"{self.name}: range {address}+{len(vals)} runs past {self.limit}")
        new = _Range(address, vals, read_only, validator, on_write, on_read)
        with self._lock:
            i = bisect.bisect_left(self._starts, address)
            if i > 0 and self._ranges[i - 1].end > address:
                prev = self._ranges[i - 1]
                raise ValueError(
                    f"{self.name}: range at {address} overlaps {prev.start}..{prev.end - 1}"
                )
            if i < len(self._ranges) and self._ranges[i].start < new.end:
                nxt = self._ranges[i]
                raise ValueError(
                    f"{self.name}: range at {address} overlaps {nxt.start}..{nxt.end - 1}"
                )
            self.version += 1
            self._ranges.insert(i, new)
            self._starts.insert(i, address)

    def _find(self, address: int) -> _Range | None:
        i = bisect.bisect_right(self._starts, address) - 1
        if i >= 0 and address < self._ranges[i].end:
            return self._ranges[i]
        return None

    def _holding(self, address: int) -> _Range:
        r = self._find(address)
        if r is None:
            raise KeyError(f"{self.name}: no range holds address {address}")
        return r

    def __contains__(self, address: object) -> bool:
        return isinstance(address, int) and self._find(address) is not None

    def ranges(self) -> list[tuple[int, int]]:
        """``[(first address, count), ...]`` in address order."""
        with self._lock:
            return [(r.start, r.end - r.start) for r in self._ranges]

    def get(self, address: int) -> Value:
        """The value at ``address`` (KeyError outside every range)."""
        with self._lock:
            r = self._find(address)
            if r is None:
                raise KeyError(f"{self.name}: no range holds address {address}")
            return r.values[address - r.start]

    def set(self, address: int, value: object) -> None:
        """Store a value as the owner (no read-only check, validator or callback)."""
        with self._lock:
            r = self._find(address)
            if r is None:
                raise KeyError(f"{self.name}: no range holds address {address}")
            self.version += 1
            r.values[address - r.start] = self._value(address, value)

    def get_many(self, address: int, count: int) -> list[Value]:
        """``count`` values from ``address`` on (KeyError at the first address outside
        every range)."""
        with self._lock:
            out: list[Value] = []
            r: _Range | None = None
            for a in range(address, address + count):
                if r is None or not r.start <= a < r.end:
                    r = self._holding(a)
                out.append(r.values[a - r.start])
            return out

    def set_many(self, address: int, values: Iterable[object]) -> None:
        """`set` for each of ``values``, from ``address`` on, under one lock."""
        self.set_each(zip(itertools.count(address), values))

    def set_each(self, values: Mapping[int, object] | Iterable[tuple[int, object]]) -> None:
        """`set` for each ``address: value`` (a mapping or pairs), in order, under one
        lock: the owner's bulk write (a simulator's refresh).  As a loop of `set`: the
        values before a bad address (KeyError) or value (ValueError) stay stored."""
        items = values.items() if isinstance(values, Mapping) else values
        with self._lock:
            self.version += 1
            r: _Range | None = None
            check = self.bits
            for a, v in items:
                if r is None or not r.start <= a < r.end:
                    r = self._holding(a)
                # a plain int in 0..65535 is what `_value` would return for a register
                if check or type(v) is not int or not 0 <= v <= 0xFFFF:
                    v = self._value(a, v)
                r.values[a - r.start] = v

    # ---------------------------------------------------------------- requests

    def _segments(self, address: int, count: int) -> list[_Segment]:
        out: list[_Segment] = []
        pos, end = address, address + count
        while pos < end:
            r = self._find(pos)
            if r is None:
                raise SlaveException(2, f"{self.name}: address {pos} is outside every range")
            n = min(end, r.end) - pos
            out.append((r, pos - r.start, n))
            pos += n
        return out

    def check_read(self, address: int, count: int) -> list[_Segment]:
        """SlaveException(2) unless every address is served."""
        return self._segments(address, count)

    def read(self, address: int, count: int) -> list[Value]:
        """A request's read: ``on_read`` first (exception 4 if it fails)."""
        with self._lock:
            segments = self._segments(address, count)
            for r, i, n in segments:
                if r.on_read is not None:
                    _call(self.name, r.on_read, r.start + i, n)
            out: list[Value] = []
            for r, i, n in segments:
                out += r.values[i : i + n]
            return out

    def check_write(self, address: int, values: list[Value]) -> list[_Segment]:
        """Exception 2 for an unserved address, 3 for read-only or rejected values."""
        segments = self._segments(address, len(values))
        k = 0
        for r, i, n in segments:
            if r.read_only:
                raise SlaveException(3, f"{self.name}: address {r.start + i} is read-only")
            if r.validator is not None:
                for j in range(n):
                    a, v = r.start + i + j, values[k + j]
                    try:
                        ok = r.validator(a, v)
                    except SlaveException:
                        raise
                    except Exception as exc:
                        raise SlaveException(
                            4, f"{self.name}: validator failed at {a}: {exc!r}"
                        ) from exc
                    if not ok:
                        raise SlaveException(3, f"{self.name}: value {v!r} rejected at address {a}")
            k += n
        return segments

    def write(self, address: int, values: list[Value]) -> None:
        """A request's write: all or nothing."""
        with self._lock:
            segments = self.check_write(address, values)
            self.version += 1
            old: list[tuple[_Range, int, list[Value]]] = []
            k = 0
            for r, i, n in segments:
                old.append((r, i, r.values[i : i + n]))
                r.values[i : i + n] = values[k : k + n]
                k += n
            k = 0
            try:
                for r, i, n in segments:
                    if r.on_write is not None:
                        _call(self.name, r.on_write, r.start + i, list(values[k : k + n]))
                    k += n
            except SlaveException:
                self.version += 1
                for r, i, vals in old:
                    r.values[i : i + len(vals)] = vals
                raise


def _call(table: str, callback: Callable[[int, Any], object], address: int, arg: Any) -> None:
    try:
        callback(address, arg)
    except SlaveException:
        raise
    except Exception as exc:
        raise SlaveException(4, f"{table}: callback failed at {address}: {exc!r}") from exc


class DataStore:
    """Coils, discrete inputs, holding registers, input registers (and files)."""

    def __init__(self) -> None:
        self.lock = StoreLock()
        self.coils = Table("coils", True, self.lock)
        self.discrete_inputs = Table("discrete_inputs", True, self.lock)
        self.holding_registers = Table("holding_registers", False, self.lock)
        self.input_registers = Table("input_registers", False, self.lock)
        #: FC 20/21 files: file number -> Table of records (0..9999)
        self.files: dict[int, Table] = {}

    def add_file(
        self, number: int, values: Iterable[object], start: int = 0, **options: object
    ) -> Table:
        """Serve file ``number`` (1..65535) with records ``start``.. (FC 20/21)."""
        if isinstance(number, bool) or not isinstance(number, int) or not 1 <= number <= 0xFFFF:
            raise ValueError(f"a file number is 1..65535, not {number!r}")
        with self.lock:
            table = self.files.get(number)
            if table is None:
                table = self.files[number] = Table(f"file {number}", False, self.lock, limit=9999)
            table.add_range(start, values, **options)  # type: ignore[arg-type]
            return table

    def file(self, number: int) -> Table:
        """The Table of file ``number`` (SlaveException(2) if not served)."""
        table = self.files.get(number)
        if table is None:
            raise SlaveException(2, f"file {number} does not exist")
        return table

    def table(self, name: str) -> Table:
        tables = {
            "coils": self.coils,
            "discrete_inputs": self.discrete_inputs,
            "holding_registers": self.holding_registers,
            "input_registers": self.input_registers,
        }
        try:
            return tables[name]
        except KeyError:
            raise ValueError(f"no table {name!r}; tables: {', '.join(tables)}") from None


__all__ = ["DataStore", "Mirror", "StoreLock", "Table"]
