"""The lock of a bus directory: one running bus per directory.

``DIR/.pyrtu-vbus.lock`` holds the owner's pid and an exclusive ``flock``.  The
kernel drops the lock when its owner dies, so a lock file left by a dead bus is
taken over; a live one makes `BusDirectoryBusy`.  On a filesystem without
``flock`` the pid alone decides (a pid that no longer runs is stale).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os

__all__ = ["LOCK_NAME", "BusDirectoryBusy", "DirectoryLock"]

LOCK_NAME = ".pyrtu-vbus.lock"


class BusDirectoryBusy(OSError):
    """Another running bus owns the directory (``.directory``, ``.pid``)."""

    def __init__(self, directory: str, pid: int | None) -> None:
        who = f"pid {pid}" if pid is not None else "another process"
        super().__init__(
            errno.EBUSY,
            f"{directory}: another virtual bus ({who}) runs in this directory;"
            " stop it or choose another directory",
        )
        self.directory = directory
        self.pid = pid

    def __str__(self) -> str:
        return str(self.args[1])


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text else None
    except (OSError, ValueError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class DirectoryLock:
    """Take the lock of ``directory`` (`BusDirectoryBusy` if a live bus has it)."""

    def __init__(self, directory: str) -> None:
        self.directory = directory
        self.path = os.path.join(directory, LOCK_NAME)
        self._fd = -1
        for _ in range(10):  # the owner may remove the file between open and flock
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise OSError(
                    exc.errno,
                    f"cannot create the lock file {LOCK_NAME} ({exc.strerror})",
                    directory,
                ) from None
            try:
                self._take(fd)
                if os.path.samestat(os.fstat(fd), os.stat(self.path)):
                    break
            except FileNotFoundError:
                pass
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)
        else:  # pragma: no cover - a directory that keeps changing under us
            raise BusDirectoryBusy(directory, None)
        self._fd = fd
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)

    def _take(self, fd: int) -> None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BusDirectoryBusy(self.directory, _read_pid(fd)) from None
        except OSError as exc:
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
                raise
            pid = _read_pid(fd)  # no flock here: the pid decides
            if pid is not None and pid != os.getpid() and _alive(pid):
                raise BusDirectoryBusy(self.directory, pid) from None

    def release(self) -> None:
        """Remove the lock file and drop the lock (idempotent)."""
        if self._fd < 0:
            return
        with contextlib.suppress(OSError):
            if os.path.samestat(os.fstat(self._fd), os.stat(self.path)):
                os.unlink(self.path)
        os.close(self._fd)
        self._fd = -1
