"""The hub: N pseudo-terminal drops on one simulated half-duplex wire."""

from __future__ import annotations

import errno
import math
import os
import select
import shutil
import tempfile
import termios
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import fields, replace
from types import TracebackType

from ..line import LineConfig
from ..timing import bits_per_char
from ._lock import DirectoryLock
from ._os import OpenWatch, open_pty, set_realtime, set_timer_slack
from ._state import (
    BusCounters,
    DropCounters,
    DropState,
    normalize_parity,
    pending_input,
)
from .capture import CaptureHeader, CaptureWriter
from .faults import FaultCounters, Faults
from .wire import Wire

__all__ = ["MAX_DROPS", "BusCounters", "DropCounters", "VirtualBus"]

#: a Modbus serial line has at most 247 slaves and a master ([SL] 2.2): each drop
#: is a pseudo-terminal, a resource of the whole system, so a bus has at most this many
MAX_DROPS = 248

_ns = time.perf_counter_ns
#: Wake this long before a delivery and spin the rest: select() wakes late by tens
#: of microseconds, a few with real-time priority.
_SPIN_NS = 50_000
_SPIN_RT_NS = 20_000
_READ_SIZE = 4096
#: Wake at least this often when idle: a thread that sleeps longer wakes slower
#: (CPU idle states, VM halts), which delays noticing a client's write.
_IDLE_TICK = 0.002
#: ... for this long after the last activity (and after start).
_WARM_NS = 2_000_000_000
#: Compensated pseudo-terminal latencies (s): client write -> hub read, and hub
#: write -> client read (typical medians measured on Linux VMs; see docs/vbus.md).
DEFAULT_LATENCY = (70e-6, 40e-6)


def _wait_readable(fds: list[int], timeout: float | None) -> list[int]:
    """select() with microsecond timeouts; poll() when an fd is beyond FD_SETSIZE."""
    try:
        if max(fds) < 1024:
            return select.select(fds, [], [], timeout)[0]
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        ms = None if timeout is None else math.ceil(timeout * 1000)
        return [fd for fd, _ in poller.poll(ms)]
    except (OSError, ValueError):
        return []  # an fd closed under us (shutdown); the loop re-reads the state


class VirtualBus:
    """A virtual RS-485 bus: `drops` pseudo-terminals sharing one half-duplex wire.

    Every byte written to a drop is put on the wire one character time after the
    previous one (starting when it was written) and delivered to every other drop
    (and to the sender when its echo is on) when its last bit has been sent.  Two
    drops transmitting at once collide: overlapping characters reach receivers
    corrupted and `counters().collisions` counts the event.

    Use as a context manager (``with VirtualBus(3, baudrate=9600) as bus:``), or
    call `start` and `close`.  `paths` are stable symlinks ``DIR/drop0``... to the
    pty slaves, openable with pyserial, libmodbus, or anything else.  Clients open
    them as 8N1 or 8N2 (a pty carries no parity); the bus's own `parity`,
    `stopbits` and `bytesize` set the character time (``1 + bytesize + parity +
    stopbits`` bits).

    Parameters:
        drops: number of drops.
        baudrate, parity, stopbits, bytesize: the wire's character format.
        directory: where the ``dropN`` symlinks go (default: a new temporary
            directory, removed by `close`).
        echo: drops that receive their own transmissions.
        faults: `Faults` for every drop; drop_faults: per-drop `Faults` (replace
            the global ones for that drop).
        capture: path of a capture file (format in `pyrtu.vbus.capture`).
        realtime: try SCHED_FIFO for the hub thread (silently skipped when not
            permitted; `realtime` attribute tells).
        latency: ``(client->hub, hub->client)`` pseudo-terminal latencies in
            seconds that the hub compensates: a byte's character starts that much
            before the hub read it, and deliveries are written that much before
            their time.  ``(0, 0)`` gives the raw schedule.

    The hub is a daemon thread of this process and shares the GIL: a thread that
    computes for milliseconds without releasing it delays deliveries.  For timing
    work, run the bus as its own process (``pyrtu vbus``).
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
        realtime: bool = True,
        latency: tuple[float, float] = DEFAULT_LATENCY,
        line: LineConfig | None = None,
    ) -> None:
        if line is not None:  # the line's byte format sets the character time
            if not isinstance(line, LineConfig):
                raise TypeError(f"line must be a LineConfig, not {type(line).__name__}")
            baudrate, parity = line.baudrate, line.parity
            stopbits, bytesize = int(line.stopbits), line.bytesize
        if isinstance(drops, bool) or not isinstance(drops, int) or not 1 <= drops <= MAX_DROPS:
            raise ValueError(
                f"a bus has 1..{MAX_DROPS} drops (247 slaves and a master), not {drops!r}"
            )
        if baudrate <= 0:
            raise ValueError("baudrate must be positive")
        if bytesize not in (5, 6, 7, 8) or stopbits not in (1, 2):
            raise ValueError("bytesize must be 5..8 and stopbits 1 or 2")
        self.baudrate = baudrate
        self.parity = normalize_parity(parity)
        self.stopbits = stopbits
        self.bytesize = bytesize
        self.bits = bits_per_char(self.parity, stopbits, bytesize)
        self.char_ns = round(self.bits * 1e9 / baudrate)
        self._directory = directory
        self._own_dir = False
        self._dir_lock: DirectoryLock | None = None
        self._capture_path = capture
        self._capture: CaptureWriter | None = None
        echo_set = set(echo)
        self._drops = [DropState(i, i in echo_set) for i in range(drops)]
        for i in echo_set | set(drop_faults or {}):
            self._check(i)
        for d in self._drops:
            f = (drop_faults or {}).get(d.index, faults)
            d.set_faults(f)
            if f is not None and f.unplug_after is not None:
                d.unplug_left = f.unplug_after
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._stop = False
        self._wake_r = self._wake_w = -1
        self._watch: OpenWatch | None = None
        self.t0_ns = 0
        self.error: BaseException | None = None
        self._want_realtime = realtime
        if min(latency) < 0 or max(latency) > 0.01:
            raise ValueError("latency compensation must be within [0, 10 ms]")
        self._anchor_ns = round(latency[0] * 1e9)
        self._wire = Wire(self._drops, self.char_ns, round(latency[1] * 1e9))
        #: True when the hub thread got real-time scheduling (SCHED_FIFO, priority 1)
        self.realtime = False
        self._spin_ns = _SPIN_NS

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
            try:
                os.makedirs(self._directory, exist_ok=True)
            except FileExistsError:
                raise NotADirectoryError(
                    errno.ENOTDIR, "not a directory", self._directory
                ) from None
        # one bus per directory: refuse before touching another bus's drops
        self._dir_lock = DirectoryLock(self._directory)
        self._watch = OpenWatch()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        try:
            for d in self._drops:
                self._plug(d)
            self.t0_ns = self._wire.t0_ns = _ns()
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
                self._wire.capture = self._capture
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
            if self._dir_lock is not None:
                self._dir_lock.release()
                self._dir_lock = None
            if self._own_dir and self._directory is not None:
                shutil.rmtree(self._directory, ignore_errors=True)
                self._directory = None
                self._own_dir = False

    def _plug(self, d: DropState) -> None:
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

    def _unplug_now(self, d: DropState, count: bool = True) -> None:
        if not d.alive:
            return
        d.alive = False
        d.cut = True
        d.txq.clear()
        d.last = None
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
                self._wire.events.append((_ns(), drop))
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

    def clients(self, drop: int) -> int:
        """How many open handles clients have on the drop (-1: not tracked here).

        Tracked with inotify: a drop nobody has open does not queue bytes, like a
        closed serial port, so a late opener reads no stale data.
        """
        self._check(drop)
        with self._lock:
            d = self._drops[drop]
            return d.clients if d.watched else -1

    def wait_clients(self, drop: int, count: int = 1, timeout: float = 2.0) -> bool:
        """Wait until the hub has seen `count` client handles open on `drop`."""
        deadline = time.monotonic() + timeout
        while True:
            n = self.clients(drop)
            if n < 0 or n >= count:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.0005)

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
                wire_bytes=self._wire.wire_bytes,
                collisions=self._wire.collisions,
                collided_bytes=self._wire.collided,
                faults=totals,
                drops=drops,
            )

    def idle(self) -> bool:
        """True when nothing is on or queued for the wire and nothing is held."""
        with self._lock:
            if self._wire.busy():
                return False
            return not any(
                d.alive and d.pty is not None and pending_input(d.pty.master) for d in self._drops
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
        if self._want_realtime:
            self.realtime = set_realtime(1)
        self._spin_ns = _SPIN_RT_NS if self.realtime else _SPIN_NS
        try:
            self._loop()
        except BaseException as exc:  # pragma: no cover - reported to the owner
            self.error = exc
            raise

    def _loop(self) -> None:
        active_until = _ns() + _WARM_NS
        while not self._stop:
            now = _ns()
            with self._lock:
                for i in self._wire.service(now):
                    self._unplug_now(self._drops[i])
                deadline = self._wire.deadline()
                rfds = [d.pty.master for d in self._drops if d.alive and d.pty is not None]
                watch_fd = self._watch.fd if self._watch is not None else -1
            rfds.append(self._wake_r)
            if watch_fd >= 0:
                rfds.append(watch_fd)
            wait: float | None = None
            if deadline is not None:
                remaining = deadline - _ns()
                if remaining <= self._spin_ns:
                    self._spin(deadline)
                    continue
                wait = (remaining - self._spin_ns) / 1e9
            if now < active_until and (wait is None or wait > _IDLE_TICK):
                wait = _IDLE_TICK
            ready = _wait_readable(rfds, wait)
            if ready:
                active_until = _ns() + _WARM_NS
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
                    self._wire.transmit(d, data, _ns() - self._anchor_ns)

    def _client_event(self, d: DropState, delta: int) -> None:
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
