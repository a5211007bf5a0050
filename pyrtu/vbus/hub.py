"""The hub: N pseudo-terminal drops on one simulated half-duplex wire."""

from __future__ import annotations

import errno
import heapq
import os
import select
import shutil
import tempfile
import termios
import threading
import time
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from types import TracebackType

from ._os import OpenWatch, Pty, open_pty, set_timer_slack
from .capture import CaptureHeader, CaptureWriter
from .faults import FaultCounters, Faults, TxFaults, collision_byte

__all__ = ["VirtualBus", "BusCounters", "DropCounters", "bits_per_char"]

_ns = time.perf_counter_ns
#: Wake this long before a delivery and spin the rest (select wakes late by tens of us).
_SPIN_NS = 120_000
_READ_SIZE = 4096


def bits_per_char(bytesize: int = 8, parity: str = "E", stopbits: float = 1) -> int:
    """Bits on the wire per character: start + data + parity + stop (10 or 11 for RTU)."""
    p = _parity(parity)
    return round(1 + bytesize + (0 if p == "N" else 1) + stopbits)


def _parity(parity: str) -> str:
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


class _Char:
    __slots__ = ("start", "end", "src", "byte", "mask", "dead")

    def __init__(self, start: int, end: int, src: int, byte: int) -> None:
        self.start = start
        self.end = end
        self.src = src
        self.byte = byte
        self.mask = -1  # -1: intact, else the byte it collided with
        self.dead = False


class _Drop:
    def __init__(self, index: int, echo: bool) -> None:
        self.index = index
        self.echo = echo
        self.pty: Pty | None = None
        self.link: str | None = None
        self.alive = False
        self.clients = 0
        self.watched = False
        self.counters = DropCounters()
        self.tx: TxFaults | None = None
        self.batch_ns = 0
        self.batch_bytes = 62
        self.tx_free = 0
        self.inflight: deque[_Char] = deque()
        self.unplug_left: int | None = None
        self.cut = False
        self.hold = bytearray()
        self.hold_deadline: int | None = None
        self.out = bytearray()
        self.episode = -1

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


class VirtualBus:
    """A virtual RS-485 bus: `drops` pseudo-terminals sharing one half-duplex wire.

    Every byte written to a drop is put on the wire one character time after the
    previous one (starting when it was written) and delivered to every other drop
    (and to the sender when its echo is on) when its last bit has been sent.  Two
    drops transmitting at once collide: overlapping characters reach receivers
    corrupted and `counters().collisions` counts the event.

    Use as a context manager (``with VirtualBus(3, baudrate=9600) as bus:``), or
    call `start` and `close`.  `paths` are stable symlinks ``DIR/drop0``... to the
    pty slaves, openable with pyserial, libmodbus, or anything else.  Clients must
    open them as 8N1 or 8N2 (a pty rejects parity); the bus's own `parity` only
    sets the character time.
    """

    def __init__(
        self,
        drops: int = 2,
        *,
        baudrate: int = 19200,
        parity: str = "E",
        stopbits: int = 1,
        bytesize: int = 8,
        directory: str | None = None,
        echo: Iterable[int] = (),
        faults: Faults | None = None,
        drop_faults: Mapping[int, Faults] | None = None,
        capture: str | None = None,
    ) -> None:
        if drops < 1:
            raise ValueError("a bus needs at least one drop")
        if baudrate <= 0:
            raise ValueError("baudrate must be positive")
        if bytesize not in (5, 6, 7, 8) or stopbits not in (1, 2):
            raise ValueError("bytesize must be 5..8 and stopbits 1 or 2")
        self.baudrate = baudrate
        self.parity = _parity(parity)
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.bits = bits_per_char(bytesize, self.parity, stopbits)
        self.char_ns = round(self.bits * 1e9 / baudrate)
        self._directory = directory
        self._own_dir = False
        self._capture_path = capture
        self._capture: CaptureWriter | None = None
        echo_set = set(echo)
        self._drops = [_Drop(i, i in echo_set) for i in range(drops)]
        for i in echo_set | set(drop_faults or {}):
            self._check(i)
        for d in self._drops:
            f = (drop_faults or {}).get(d.index, faults)
            d.set_faults(f)
            if f is not None and f.unplug_after is not None:
                d.unplug_left = f.unplug_after
        self._heap: list[tuple[int, int, _Char]] = []
        self._seq = 0
        self._events: list[tuple[int, int]] = []  # (time, drop) unplug events
        self._wire_bytes = 0
        self._collisions = 0
        self._collided = 0
        self._coll_until = -1
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop = False
        self._wake_r = self._wake_w = -1
        self._watch: OpenWatch | None = None
        self.t0_ns = 0
        self.error: BaseException | None = None

    # -- properties ------------------------------------------------------------

    @property
    def char_time(self) -> float:
        """Seconds per character (bits per character / baud rate)."""
        return self.char_ns / 1e9

    @property
    def directory(self) -> str:
        if self._directory is None:
            raise RuntimeError("bus not started")
        return self._directory

    @property
    def paths(self) -> list[str]:
        """Stable paths of the drops (``DIR/dropN`` symlinks to the pty slaves)."""
        return [self.path(i) for i in range(len(self._drops))]

    @property
    def tty_paths(self) -> list[str]:
        """The ``/dev/pts/N`` paths of the drops (empty string once unplugged)."""
        return [d.pty.path if d.pty else "" for d in self._drops]

    def path(self, drop: int) -> str:
        self._check(drop)
        return os.path.join(self.directory, f"drop{drop}")

    def __len__(self) -> int:
        return len(self._drops)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def now(self) -> float:
        """The bus clock (`time.perf_counter`), in seconds."""
        return _ns() / 1e9

    def _check(self, drop: int) -> None:
        if not 0 <= drop < len(self._drops):
            raise IndexError(f"no drop {drop} on a {len(self._drops)}-drop bus")

    # -- life cycle ------------------------------------------------------------

    def __enter__(self) -> VirtualBus:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def start(self) -> VirtualBus:
        """Create the drops and start the hub thread."""
        if self._thread is not None:
            raise RuntimeError("bus already started")
        if self._directory is None:
            self._directory = tempfile.mkdtemp(prefix="pyrtu-vbus-")
            self._own_dir = True
        else:
            os.makedirs(self._directory, exist_ok=True)
        self._watch = OpenWatch()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        try:
            for d in self._drops:
                self._plug(d)
            self.t0_ns = _ns()
            if self._capture_path is not None:
                header = CaptureHeader(
                    baudrate=self.baudrate,
                    bytesize=self.bytesize,
                    parity=self.parity,
                    stopbits=self.stopbits,
                    bits=self.bits,
                    char_ns=self.char_ns,
                    drops=len(self._drops),
                    start_unix_ns=time.time_ns(),
                )
                self._capture = CaptureWriter(self._capture_path, header)
        except BaseException:
            self._teardown()
            raise
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="pyrtu-vbus", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the hub and remove the drops (idempotent)."""
        thread = self._thread
        if thread is not None:
            self._stop = True
            self._wake()
            thread.join(5.0)
            self._thread = None
        self._teardown()

    def _teardown(self) -> None:
        with self._lock:
            for d in self._drops:
                self._unplug_now(d, count=False)
            if self._capture is not None:
                self._capture.close()
                self._capture = None
            if self._watch is not None:
                self._watch.close()
                self._watch = None
            for fd in (self._wake_r, self._wake_w):
                if fd >= 0:
                    os.close(fd)
            self._wake_r = self._wake_w = -1
            if self._own_dir and self._directory is not None:
                shutil.rmtree(self._directory, ignore_errors=True)
                self._directory = None
                self._own_dir = False

    def _plug(self, d: _Drop) -> None:
        pty = open_pty()
        d.pty = pty
        d.alive = True
        d.cut = False
        d.clients = 0
        d.counters.unplugged = False
        d.tx_free = 0
        d.watched = self._watch is not None and self._watch.add(pty.path, d.index)
        link = os.path.join(self.directory, f"drop{d.index}")
        tmp = f"{link}.{os.getpid()}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(pty.path, tmp)
        os.replace(tmp, link)
        d.link = link

    def _unplug_now(self, d: _Drop, count: bool = True) -> None:
        if not d.alive:
            return
        d.alive = False
        d.cut = True
        for ch in d.inflight:
            ch.dead = True
        d.inflight.clear()
        d.hold.clear()
        d.hold_deadline = None
        d.out.clear()
        d.unplug_left = None
        if self._capture is not None:
            self._capture.end_run(d.index)
        if self._watch is not None:
            self._watch.remove(d.index)
        if d.link is not None:
            try:
                if os.path.islink(d.link):
                    os.unlink(d.link)
            except OSError:
                pass
            d.link = None
        if d.pty is not None:
            d.pty.close()
            d.pty = None
        d.counters.unplugged = True
        if count:
            d.counters.faults.unplugs += 1

    def _wake(self) -> None:
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"\0")
            except OSError:
                pass

    # -- control ---------------------------------------------------------------

    def unplug(self, drop: int, after_bytes: int = 0) -> None:
        """Make a drop go away, like a USB adapter pulled out.

        With ``after_bytes=N`` the drop vanishes after it has put N more bytes on
        the wire (mid-frame when N is less than the frame length): the rest of what
        its client writes is never sent, its pty is closed (the client's reads and
        writes fail) and its symlink is removed.
        """
        self._check(drop)
        if after_bytes < 0:
            raise ValueError("after_bytes must be >= 0")
        with self._lock:
            d = self._drops[drop]
            if not d.alive:
                return
            if after_bytes == 0:
                d.cut = True
                self._events.append((_ns(), drop))
            else:
                d.unplug_left = after_bytes
        self._wake()

    def replug(self, drop: int) -> str:
        """Bring an unplugged drop back (a new pty behind the same ``dropN`` path)."""
        self._check(drop)
        with self._lock:
            d = self._drops[drop]
            if not d.alive:
                self._plug(d)
        self._wake()
        return self.path(drop)

    def set_echo(self, drop: int, on: bool = True) -> None:
        """Turn the local echo of a drop on or off."""
        self._check(drop)
        with self._lock:
            self._drops[drop].echo = on

    def set_faults(self, faults: Faults | None, drop: int | None = None) -> None:
        """Replace the faults of one drop (or of every drop when `drop` is None)."""
        with self._lock:
            targets = self._drops if drop is None else [self._drops[drop]]
            for d in targets:
                d.set_faults(faults)
                if faults is not None and faults.unplug_after is not None:
                    d.unplug_left = faults.unplug_after

    def counters(self) -> BusCounters:
        """A snapshot of the counters."""
        with self._lock:
            drops = tuple(
                replace(d.counters, faults=replace(d.counters.faults)) for d in self._drops
            )
            totals = {f.name: 0 for f in fields(FaultCounters)}
            for dc in drops:
                for name in totals:
                    totals[name] += getattr(dc.faults, name)
            return BusCounters(
                wire_bytes=self._wire_bytes,
                collisions=self._collisions,
                collided_bytes=self._collided,
                faults=totals,
                drops=drops,
            )

    def idle(self) -> bool:
        """True when nothing is on or queued for the wire and nothing is held."""
        with self._lock:
            return not self._heap and not self._events and not any(
                d.hold for d in self._drops
            )

    def wait_idle(self, timeout: float = 5.0, settle: float = 0.0) -> bool:
        """Wait until `idle` (and has stayed so for `settle` seconds)."""
        deadline = time.monotonic() + timeout
        quiet_since: float | None = None
        while time.monotonic() < deadline:
            if self.idle():
                now = time.monotonic()
                if quiet_since is None:
                    quiet_since = now
                if now - quiet_since >= settle:
                    return True
            else:
                quiet_since = None
            time.sleep(0.001)
        return False

    # -- hub thread --------------------------------------------------------------

    def _run(self) -> None:
        set_timer_slack(1000)
        try:
            self._loop()
        except BaseException as exc:  # pragma: no cover - reported to the owner
            self.error = exc
            raise

    def _loop(self) -> None:
        while not self._stop:
            now = _ns()
            with self._lock:
                self._service(now)
                deadline = self._deadline()
                rfds = [d.pty.master for d in self._drops if d.alive and d.pty is not None]
                watch_fd = self._watch.fd if self._watch is not None else -1
            rfds.append(self._wake_r)
            if watch_fd >= 0:
                rfds.append(watch_fd)
            wait: float | None = None
            if deadline is not None:
                remaining = deadline - _ns()
                if remaining <= _SPIN_NS:
                    self._spin(deadline)
                    continue
                wait = (remaining - _SPIN_NS) / 1e9
            try:
                ready, _, _ = select.select(rfds, [], [], wait)
            except (OSError, ValueError):
                continue  # an fd closed under us (unplug from another thread)
            if ready:
                self._on_ready(ready, watch_fd)

    def _spin(self, deadline: int) -> None:
        # Brief busy-wait for the last stretch; sleep(0) lets other threads run.
        while _ns() < deadline:
            time.sleep(0)

    def _on_ready(self, ready: list[int], watch_fd: int) -> None:
        with self._lock:
            if watch_fd in ready and self._watch is not None:
                for key, delta in self._watch.read():
                    self._client_event(self._drops[key], delta)
            if self._wake_r in ready:
                try:
                    os.read(self._wake_r, 4096)
                except OSError:
                    pass
            for d in self._drops:
                if not d.alive or d.pty is None or d.pty.master not in ready:
                    continue
                try:
                    data = os.read(d.pty.master, _READ_SIZE)
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EIO, errno.EINTR):
                        continue
                    raise
                if data:
                    self._transmit(d, data, _ns())

    def _client_event(self, d: _Drop, delta: int) -> None:
        before = d.clients
        d.clients = max(0, d.clients + delta)
        if (before == 0) != (d.clients == 0) and d.pty is not None:
            # first client arrived or last one left: nothing stale stays queued
            try:
                termios.tcflush(d.pty.slave, termios.TCIFLUSH)
            except termios.error:
                pass
            d.hold.clear()
            d.hold_deadline = None

    def _deadline(self) -> int | None:
        t: int | None = self._heap[0][0] if self._heap else None
        for d in self._drops:
            if d.hold_deadline is not None and (t is None or d.hold_deadline < t):
                t = d.hold_deadline
        for when, _ in self._events:
            if t is None or when < t:
                t = when
        return t

    # -- transmit side -------------------------------------------------------------

    def _transmit(self, d: _Drop, data: bytes, now: int) -> None:
        if d.cut:
            return
        c = self.char_ns
        t = max(now, d.tx_free)
        tx = d.tx
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
                if v is not None:
                    self._put(d, t, v)
                t += c
            d.counters.tx_bytes += 1
            if d.unplug_left is not None:
                d.unplug_left -= 1
                if d.unplug_left <= 0:
                    self._cut(d, t)
                    break
        d.tx_free = t

    def _cut(self, d: _Drop, t: int) -> None:
        """The drop transmits nothing more and goes away at `t`."""
        d.unplug_left = None
        d.cut = True
        self._events.append((t, d.index))

    def _put(self, d: _Drop, start: int, byte: int) -> None:
        end = start + self.char_ns
        ch = _Char(start, end, d.index, byte)
        for o in self._drops:
            if o is d or not o.inflight:
                continue
            for oc in o.inflight:
                if oc.start >= end:
                    break
                if oc.end > start and not oc.dead:
                    self._collide(ch, oc, d, o)
        d.inflight.append(ch)
        self._seq += 1
        heapq.heappush(self._heap, (end, self._seq, ch))

    def _collide(self, ch: _Char, oc: _Char, d: _Drop, o: _Drop) -> None:
        if ch.mask < 0:
            ch.mask = oc.byte
        if oc.mask < 0:
            oc.mask = ch.byte
        if ch.start >= self._coll_until:
            self._collisions += 1
        self._coll_until = max(self._coll_until, ch.end, oc.end)
        for x in (d, o):
            if x.episode != self._collisions:
                x.episode = self._collisions
                x.counters.collisions += 1

    # -- receive side ---------------------------------------------------------------

    def _service(self, now: int) -> None:
        heap = self._heap
        drops = self._drops
        cap = self._capture
        touched = False
        while heap and heap[0][0] <= now:
            _, _, ch = heapq.heappop(heap)
            if ch.dead:
                continue
            src = drops[ch.src]
            if src.inflight and src.inflight[0] is ch:
                src.inflight.popleft()
            value = ch.byte if ch.mask < 0 else collision_byte(ch.byte, ch.mask)
            self._wire_bytes += 1
            if ch.mask >= 0:
                self._collided += 1
                src.counters.collided_bytes += 1
            if cap is not None:
                cap.add(ch.src, ch.start - self.t0_ns, value, ch.mask >= 0)
            for r in drops:
                if not r.alive or (r is src and not r.echo):
                    continue
                if r.batch_ns:
                    if not r.hold:
                        r.hold_deadline = ch.end + r.batch_ns
                    r.hold.append(value)
                    if len(r.hold) >= r.batch_bytes:
                        self._release(r)
                else:
                    r.out.append(value)
            touched = True
        for r in drops:
            if r.hold_deadline is not None and r.hold_deadline <= now:
                self._release(r)
            if r.out:
                self._write(r)
        if touched and cap is not None:
            for i in cap.pending():
                if not drops[i].inflight:
                    cap.end_run(i)
        if self._events:
            due = [e for e in self._events if e[0] <= now]
            if due:
                self._events = [e for e in self._events if e[0] > now]
                for _, i in due:
                    self._unplug_now(drops[i])

    def _release(self, r: _Drop) -> None:
        r.out += r.hold
        r.hold.clear()
        r.hold_deadline = None
        r.counters.faults.batches += 1

    def _write(self, r: _Drop) -> None:
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
