"""Operating-system helpers for the hub: pseudo-terminals, inotify, timer slack."""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import struct
import termios
import tty
from dataclasses import dataclass

from pyrtu.drivers._slack import set_timer_slack

__all__ = ["OpenWatch", "Pty", "open_pty", "set_realtime", "set_timer_slack"]

_libc: ctypes.CDLL | None
try:
    _libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
except OSError:  # pragma: no cover - no libc to load
    _libc = None

_IN_NONBLOCK = os.O_NONBLOCK
_IN_CLOEXEC = os.O_CLOEXEC
IN_OPEN = 0x020
IN_CLOSE_WRITE = 0x008
IN_CLOSE_NOWRITE = 0x010
IN_IGNORED = 0x8000
_EVENT = struct.Struct("iIII")


def set_realtime(priority: int = 1) -> bool:
    """Give the calling thread SCHED_FIFO at `priority`, when permitted (Linux).

    Needs CAP_SYS_NICE (root) or an RLIMIT_RTPRIO allowance; returns False
    without changing anything otherwise.
    """
    setsched = getattr(os, "sched_setscheduler", None)
    fifo = getattr(os, "SCHED_FIFO", None)
    if setsched is None or fifo is None:  # pragma: no cover - not Linux
        return False
    try:
        setsched(0, fifo, os.sched_param(priority))
    except OSError:
        return False
    return True


@dataclass
class Pty:
    """A pseudo-terminal pair: the hub keeps the master and one slave-side fd."""

    master: int
    slave: int
    path: str

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


def open_pty() -> Pty:
    """Open a raw pseudo-terminal; the master is non-blocking.

    The hub keeps a slave-side fd open for the life of the drop, so the master
    never reads EIO/EOF while no client has the slave open, and the raw settings
    persist across client opens.
    """
    master, slave = os.openpty()
    try:
        tty.setraw(slave, termios.TCSANOW)
        attrs = termios.tcgetattr(slave)
        attrs[2] |= termios.CLOCAL | termios.CREAD
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        return Pty(master, slave, os.ttyname(slave))
    except BaseException:
        os.close(master)
        os.close(slave)
        raise


class OpenWatch:
    """Counts the processes' opens and closes of pty slaves through inotify.

    The hub uses it to know whether a drop has a client: a real serial port does
    not buffer what arrives while nobody has it open, and this keeps stale bytes
    from piling up in drops nobody listens to.  `fd` is -1 when inotify is not
    available (then every drop counts as listened to).
    """

    def __init__(self) -> None:
        self.fd = -1
        self._wd: dict[int, int] = {}  # watch descriptor -> key
        if _libc is None:
            return
        try:
            fd = int(_libc.inotify_init1(_IN_NONBLOCK | _IN_CLOEXEC))
        except AttributeError:  # pragma: no cover - not Linux
            return
        self.fd = fd if fd >= 0 else -1

    @property
    def available(self) -> bool:
        return self.fd >= 0

    def add(self, path: str, key: int) -> bool:
        if self.fd < 0 or _libc is None:
            return False
        mask = IN_OPEN | IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
        wd = int(_libc.inotify_add_watch(self.fd, os.fsencode(path), mask))
        if wd < 0:
            return False
        self._wd[wd] = key
        return True

    def remove(self, key: int) -> None:
        for wd, k in list(self._wd.items()):
            if k == key:
                del self._wd[wd]
                if _libc is not None and self.fd >= 0:
                    _libc.inotify_rm_watch(self.fd, wd)

    def read(self) -> list[tuple[int, int]]:
        """Pending events as ``(key, +1 open | -1 close)``."""
        out: list[tuple[int, int]] = []
        if self.fd < 0:
            return out
        while True:
            try:
                buf = os.read(self.fd, 4096)
            except BlockingIOError:
                return out
            except OSError as exc:  # pragma: no cover - defensive
                if exc.errno == errno.EINTR:
                    continue
                return out
            if not buf:
                return out
            off = 0
            while off + _EVENT.size <= len(buf):
                wd, mask, _cookie, length = _EVENT.unpack_from(buf, off)
                off += _EVENT.size + length
                key = self._wd.get(wd)
                if key is None:
                    continue
                if mask & IN_OPEN:
                    out.append((key, 1))
                if mask & (IN_CLOSE_WRITE | IN_CLOSE_NOWRITE):
                    out.append((key, -1))

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
        self._wd.clear()
