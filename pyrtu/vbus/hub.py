"""The hub: N pseudo-terminal drops on one simulated half-duplex wire."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import fields, replace

from pyrtu.core._pure.vbus import OUT, Schedule
from pyrtu.core.line import BYTE_FORMAT, LineConfig, line_from
from pyrtu.core.timing import (
    bits_per_char,
    check_baudrate,
    check_bytesize,
    check_parity,
    check_stopbits,
)

from . import _cvbus
from ._cvbus import CLoop, CSchedule
from ._hubloop import _SPIN_NS, DEFAULT_LATENCY, HubLoops
from ._lock import DirectoryLock
from ._os import OpenWatch, open_pty
from ._state import (
    BusCounters,
    DropCounters,
    DropState,
    normalize_parity,
    pending_input,
)
from .capture import CaptureHeader, CaptureWriter
from .faults import FaultCounters, Faults

__all__ = ["MAX_DROPS", "BusCounters", "DropCounters", "VirtualBus"]

#: a Modbus serial line has at most 247 slaves and a master ([SL] 2.2): each drop
#: is a pseudo-terminal, a resource of the whole system, so a bus has at most this many
MAX_DROPS = 248
_ns = time.perf_counter_ns


class VirtualBus(HubLoops):
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
        loop: ``"auto"`` (default): the C loop (csrc/rtu_vbus_io.c: the schedule and
            the pty I/O in C, no GIL) when the C core is the backend and no capture
            and no line faults are asked for, else the Python loop (the twin
            schedule, pyrtu/core/_pure/vbus.py, and a select() loop); ``"python"``
            forces the Python loop.  `loop` attribute: the one running.  A bus on
            the C loop moves to the Python loop when line faults are set on it.

    The hub is a daemon thread of this process.  On the Python loop it shares the
    GIL: a thread that computes for milliseconds without releasing it delays
    deliveries; for timing work, run the bus as its own process (``pyrtu vbus``).
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
        loop: str = "auto",
    ) -> None:
        if line is not None:  # the line's byte format sets the character time
            fmt = dict(baudrate=baudrate, parity=parity, stopbits=stopbits, bytesize=bytesize)
            line = line_from(line, "VirtualBus", **fmt)  # (not line= and keywords both)
            baudrate, parity = line.baudrate, line.parity
            stopbits, bytesize = int(line.stopbits), line.bytesize
        if isinstance(drops, bool) or not isinstance(drops, int) or not 1 <= drops <= MAX_DROPS:
            raise ValueError(
                f"a bus has 1..{MAX_DROPS} drops (247 slaves and a master), not {drops!r}"
            )
        check_baudrate(baudrate)  # the checks and words of LineConfig (pyrtu.core.timing)
        check_bytesize(bytesize)
        if check_stopbits(stopbits) not in (1, 2):  # the capture header holds 1 or 2
            raise ValueError(f"stopbits must be 1 or 2 on the virtual bus, not {stopbits!r}")
        if loop not in ("auto", "python"):
            raise ValueError(f"loop must be 'auto' or 'python', not {loop!r}")
        self.baudrate = baudrate
        self.parity = normalize_parity(check_parity(parity))
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
        self._lead_ns = round(latency[1] * 1e9)
        self._faults = [(drop_faults or {}).get(d.index, faults) for d in self._drops]
        line_faults = any(f is not None and f.line_faults for f in self._faults)
        #: which loop runs the hub: "c" or "python" (see the class docstring)
        self.loop = (
            "c"
            if loop == "auto" and _cvbus.available and capture is None and not line_faults
            else "python"
        )
        self._sched: Schedule | CSchedule = self._new_schedule()
        self._cloop: CLoop | None = None
        self._to_python = False
        for d, f in zip(self._drops, self._faults, strict=True):
            self._sched.set_echo(d.index, d.echo)
            self._apply_faults(d, f)
        #: True when the hub thread got real-time scheduling (SCHED_FIFO, priority 1)
        self.realtime = False
        self._spin_ns = _SPIN_NS

    def _new_schedule(self) -> Schedule | CSchedule:
        n = len(self._drops)
        if self.loop == "c":
            return CSchedule(n, self.char_ns, self._lead_ns)
        return Schedule(n, self.char_ns, self._lead_ns)

    def _apply_faults(self, d: DropState, f: Faults | None) -> None:
        d.set_faults(f)
        self._sched.set_batch(d.index, d.batch_ns, min(d.batch_bytes, OUT))
        if isinstance(self._sched, Schedule):
            self._sched.set_tx_faults(d.index, d.tx)
        if f is not None and f.unplug_after is not None:
            self._sched.set_unplug_after(d.index, f.unplug_after)

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

    def __exit__(self, *exc: object) -> None:
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
            if isinstance(self._sched, CSchedule):
                self._cloop = CLoop(self._sched, self._wake_r, self._watch.fd, self._anchor_ns)
            for d in self._drops:
                self._plug(d)
            self.t0_ns = _ns()
            if self._capture_path is not None and isinstance(self._sched, Schedule):
                header = CaptureHeader(
                    **{k: getattr(self, k) for k in BYTE_FORMAT},
                    bits=self.bits,
                    char_ns=self.char_ns,
                    drops=len(self._drops),
                    start_unix_ns=time.time_ns(),
                )
                self._capture = CaptureWriter(self._capture_path, header)
                self._sched.capture = self._capture
                self._sched.t0_ns = self.t0_ns
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
            self._interrupt()
            thread.join(5.0)
            self._thread = None
        self._teardown()

    def _teardown(self) -> None:
        with self._lock:
            for d in self._drops:
                self._unplug_now(d, count=False)
            if self._cloop is not None:
                self._cloop.destroy()
                self._cloop = None
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

    @contextlib.contextmanager
    def _locked(self) -> Iterator[Schedule | CSchedule]:
        """The hub's lock and, on the C loop, the I/O thread's: the schedule is ours."""
        with self._lock:
            cloop = self._cloop
            if cloop is None:
                yield self._sched
                return
            cloop.lock()
            try:
                yield self._sched
            finally:
                cloop.unlock()

    def _plug(self, d: DropState) -> None:
        pty = open_pty()
        d.pty = pty
        d.clients = 0
        d.counters.unplugged = False
        d.watched = self._watch is not None and self._watch.add(pty.path, d.index)
        with self._locked() as sched:
            sched.plug(d.index)
            if self._cloop is not None:
                self._cloop.set_fd(d.index, pty.master, d.heard)
        link = os.path.join(self.directory, f"drop{d.index}")
        tmp = f"{link}.{os.getpid()}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(pty.path, tmp)
        os.replace(tmp, link)
        d.link = link

    def _unplug_now(self, d: DropState, count: bool = True) -> None:
        with self._locked() as sched:
            if d.pty is None:
                return
            sched.unplug(d.index)
            if self._cloop is not None:
                self._cloop.set_fd(d.index, -1, False)
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

    def _interrupt(self) -> None:
        """Make the hub thread come back to Python (the C loop returns), and wake it."""
        with self._lock:
            if self._cloop is not None:
                self._cloop.stop()
        self._wake()

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
        with self._locked() as sched:
            if not sched.alive(drop):
                return
            if after_bytes == 0:
                sched.cut(drop, _ns())
            else:
                sched.set_unplug_after(drop, after_bytes)
        self._wake()

    def replug(self, drop: int) -> str:
        """Bring an unplugged drop back (a new pty behind the same ``dropN`` path)."""
        self._check(drop)
        with self._lock:
            d = self._drops[drop]
            if d.pty is None:
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
        with self._locked() as sched:
            self._drops[drop].echo = on
            sched.set_echo(drop, on)

    def set_faults(self, faults: Faults | None, drop: int | None = None) -> None:
        """Replace the faults of one drop (or of every drop when `drop` is None).

        Line faults on a bus running the C loop move it to the Python loop (the
        seeded faults are Python's `random.Random`): the schedule's state moves over.
        """
        if drop is not None:
            self._check(drop)
        if faults is not None and faults.line_faults and self._cloop is not None:
            self._move_to_python()
        with self._locked():
            targets = self._drops if drop is None else [self._drops[drop]]
            for d in targets:
                self._faults[d.index] = faults
                self._apply_faults(d, faults)
        self._wake()

    def _move_to_python(self) -> None:
        """Hand the C schedule's state to the twin and run the Python loop."""
        thread = self._thread
        if thread is not None and thread.is_alive():
            with self._lock:
                self._to_python = True
            self._interrupt()
            while self._cloop is not None and thread.is_alive():
                time.sleep(0.0005)
        else:
            with self._lock:
                self._take_over()

    def counters(self) -> BusCounters:
        """A snapshot of the counters."""
        with self._locked() as sched:
            drops = []
            for d in self._drops:
                c = sched.drop_counters(d.index)
                drops.append(
                    DropCounters(
                        tx_bytes=c["tx_bytes"],
                        rx_bytes=c["rx_bytes"],
                        collided_bytes=c["collided_bytes"],
                        collisions=c["collisions"],
                        overruns=c["overruns"],
                        unheard=c["unheard"],
                        faults=replace(d.counters.faults, batches=c["batches"]),
                        unplugged=d.counters.unplugged,
                    )
                )
            totals = {f.name: 0 for f in fields(FaultCounters)}
            for dc in drops:
                for name in totals:
                    totals[name] += getattr(dc.faults, name)
            return BusCounters(
                wire_bytes=sched.wire_bytes,
                collisions=sched.collisions,
                collided_bytes=sched.collided,
                faults=totals,
                drops=tuple(drops),
            )

    def idle(self) -> bool:
        """True when nothing is on or queued for the wire and nothing is held."""
        with self._locked() as sched:
            if sched.busy():
                return False
            return not any(d.pty is not None and pending_input(d.pty.master) for d in self._drops)

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
