"""Test helper: two pseudo-terminals joined by a forwarding thread.

``PtyLink()`` opens two pty pairs; side "a" (``path_a``) and side "b" (``path_b``)
are the tty ends that pyserial opens.  A thread copies what one side writes to the
other, records every byte with its time (``wire``), and can:

* echo a side's bytes back to it (an echoing RS-485 adapter): ``echo={"a"}``;
* rewrite or drop what goes a->b or b->a (``filters``: a function of the chunk
  returning the bytes to deliver, b"" drops);
* inject bytes as if they came from the wire (``inject``).

The tty ends are set raw at once, and kept open by the link so the ptys live as long
as the link does, whoever opens and closes them.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from typing import Any

import serial

from pyrtu import add_crc
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.protocol.datastore import DataStore

Filter = Callable[[bytes], bytes]
Answer = Callable[[bytes, int], list[tuple[float, bytes]]]


class PtyLink:
    def __init__(self, echo: set[str] | None = None) -> None:
        self.echo = set(echo or ())
        #: per side: rewrites the echo (to fake a collision), b"" drops it
        self.echo_filters: dict[str, Filter] = {}
        self._ma, self._sa = os.openpty()
        self._mb, self._sb = os.openpty()
        for fd in (self._sa, self._sb):
            tty.setraw(fd)
        self.path_a = os.ttyname(self._sa)
        self.path_b = os.ttyname(self._sb)
        self.filters: dict[str, Filter] = {}
        self.log: list[tuple[str, float, bytes]] = []  # (writer side, time, bytes)
        self._lock = threading.Lock()
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="ptylink", daemon=True)
        self._thread.start()

    def _deliver(self, fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                select.select((), (fd,), (), 0.1)
                continue
            view = view[n:]

    def _run(self) -> None:
        sides = {self._ma: ("a", self._mb), self._mb: ("b", self._ma)}
        while not self._stop:
            ready = select.select([self._ma, self._mb, self._wake_r], [], [], 0.5)[0]
            for fd in ready:
                if fd == self._wake_r:
                    continue
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                if not data:
                    continue
                side, other = sides[fd]
                with self._lock:
                    self.log.append((side, time.monotonic(), data))
                    filt = self.filters.get(side)
                if side in self.echo:
                    efilt = self.echo_filters.get(side)
                    back = efilt(data) if efilt is not None else data
                    if back:
                        self._deliver(fd, back)
                out = filt(data) if filt is not None else data
                if out:
                    self._deliver(other, out)

    def inject(self, to: str, data: bytes) -> None:
        """Bytes that arrive at side ``to`` as if from the wire (not logged)."""
        self._deliver(self._ma if to == "a" else self._mb, data)

    def wire(self, side: str) -> bytes:
        """Everything side ``side`` has written so far."""
        with self._lock:
            return b"".join(d for s, _t, d in self.log if s == side)

    def writes(self, side: str) -> list[tuple[float, bytes]]:
        with self._lock:
            return [(t, d) for s, t, d in self.log if s == side]

    def gaps(self, first: str, then: str) -> list[float]:
        """Once the link is quiet (`settle`): the times from each write of side
        ``first`` to a write of side ``then`` that follows it directly."""
        self.settle()
        with self._lock:
            log = sorted(self.log, key=lambda item: item[1])
        return [
            t2 - t1
            for (s1, t1, _), (s2, t2, _) in itertools.pairwise(log)
            if (s1, s2) == (first, then)
        ]

    def clear(self) -> None:
        with self._lock:
            self.log.clear()

    def settle(self, quiet: float = 0.02, timeout: float = 2.0) -> None:
        """Wait until nothing was written for ``quiet`` seconds."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._lock:
                last = self.log[-1][1] if self.log else 0.0
            if time.monotonic() - last >= quiet:
                return
            time.sleep(quiet / 4)

    def close(self) -> None:
        self._stop = True
        os.write(self._wake_w, b"x")
        self._thread.join(2)
        for fd in (self._ma, self._mb, self._sa, self._sb, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- helpers for the master and slave tests ---------------------------------------


def count_reads(protocol: Any, reads: list[int]) -> None:
    """From now on the length of every non-empty chunk ``protocol`` (a slave's sans-I/O
    protocol) is fed is appended to ``reads``: how many reads a request took."""
    feed = protocol.receive_data

    def counting(data: bytes, now: float) -> None:
        if data:
            reads.append(len(data))
        feed(data, now)

    protocol.receive_data = counting


def reads_per_request(port: str, reads: list[int]) -> list[int]:
    """16 reads of slave 1's registers 0-9 (`make_store`'s values, checked) by a sync
    `Master` on ``port`` at 9600 8N1: in how many reads each reached the slave (its
    protocol counted by `count_reads` into ``reads``), the first left out (the slave
    has no guess of a request's length yet)."""
    per: list[int] = []
    with Master(port, 9600, parity="N", timeout=1.0) as m:
        for _ in range(16):
            before = len(reads)
            assert m.read_holding_registers(1, 0, 10) == [1000 + i for i in range(10)]
            per.append(len(reads) - before)
    return per[1:]


def rtu(hexbytes: str) -> bytes:
    """An RTU ADU from the hex of its address and PDU (spaces allowed), CRC appended."""
    return add_crc(bytes.fromhex(hexbytes))


def make_store() -> DataStore:
    """A store with every table and a file, values derived from the address."""
    store = DataStore()
    store.coils.add_range(0, [i % 3 == 0 for i in range(100)])
    store.discrete_inputs.add_range(0, [i % 2 == 0 for i in range(100)])
    store.holding_registers.add_range(0, [1000 + i for i in range(200)])
    store.input_registers.add_range(0, [2000 + i for i in range(100)])
    store.add_file(4, [0x100 + i for i in range(20)])
    return store


@contextlib.contextmanager
def serving(path: str, **options: Any) -> Iterator[Slave]:
    """A pyrtu Slave on ``path`` (8N1) serving in its background thread."""
    options.setdefault("parity", "N")
    slave = Slave(path, **options)
    slave.start()
    try:
        yield slave
    finally:
        slave.close()
    if slave.error is not None:
        raise slave.error


class RawPort:
    """A bare pyserial port (8N1) that sends ADUs and collects what comes back."""

    def __init__(self, path: str) -> None:
        self.serial = serial.Serial(path, 19200, timeout=0)

    def send(self, data: bytes) -> None:
        self.serial.write(data)

    def collect(self, quiet: float = 0.05, timeout: float = 1.0, want: int = 0) -> bytes:
        """Bytes until ``want`` arrived (if given) or nothing came for ``quiet`` seconds."""
        out = b""
        end = time.monotonic() + timeout
        last = time.monotonic()
        while time.monotonic() < end:
            chunk = self.serial.read(4096)
            now = time.monotonic()
            if chunk:
                out += chunk
                last = now
                if want and len(out) >= want:
                    break
            elif now - last >= quiet and (not want or out):
                break
            else:
                time.sleep(0.002)
        return out

    def ask(self, adu: bytes, want: int = 0, quiet: float = 0.05) -> bytes:
        self.serial.reset_input_buffer()
        self.send(adu)
        return self.collect(quiet=quiet, want=want)

    def close(self) -> None:
        self.serial.close()

    def __enter__(self) -> RawPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ScriptedSlave:
    """A hand-written slave on side ``path``: ``answer(request_adu, n)`` returns what to
    send back as ``[(delay_seconds, bytes), ...]`` for the n-th request (0-based).
    Requests are cut from the byte stream by the CRC (RTU) or CR LF (ASCII)."""

    def __init__(self, path: str, answer: Answer) -> None:
        self.port = RawPort(path)
        self.answer = answer
        self.requests: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="scripted-slave")
        self._thread.start()

    def _run(self) -> None:
        from pyrtu import check_crc

        buf = b""
        while not self._stop.is_set():
            chunk = self.port.serial.read(4096)
            if not chunk:
                time.sleep(0.001)
                continue
            buf += chunk
            cut = 0
            if buf.startswith(b":"):
                cut = buf.find(b"\r\n") + 2 if b"\r\n" in buf else 0
            else:
                cut = next((n for n in range(4, len(buf) + 1) if check_crc(buf[:n])), 0)
            if not cut:
                continue
            request, buf = buf[:cut], buf[cut:]
            self.requests.append(request)
            for delay, data in self.answer(request, len(self.requests) - 1):
                time.sleep(delay)
                self.port.send(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.port.close()

    def __enter__(self) -> ScriptedSlave:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
