"""The twin of csrc/rtu_xfer_io.c: one master exchange on a serial descriptor, in
Python (`pyrtu.core.xfer` has the contract).  Step for step as the C file: sleep to
the send time, look for stale input, write (tcdrain on a real line), sleep to the
first read, then sleep through all but the last character and wait for it."""

from __future__ import annotations

import errno
import os
import select
import termios
import threading
import time
from typing import Any

from pyrtu.core.xfer import (
    ANSWER,
    CAPACITY,
    ERRNO,
    GONE,
    SHORT,
    STAGE_READ,
    STAGE_WRITE,
    STALE,
    XferResult,
    check_plan,
)

_now = time.monotonic
_AGAIN = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR)


class _Failed(Exception):
    """A step ended the exchange (status, err, stage)."""

    def __init__(self, status: int, err: int = 0, stage: int = 0) -> None:
        super().__init__(status)
        self.status, self.err, self.stage = status, err, stage


def _sleep_until(t: float) -> None:
    left = t - _now()
    if left > 0:
        time.sleep(left)


def _wait_fd(fd: int, events: int, t: float) -> bool:
    """``events`` on ``fd`` before ``t`` (a past ``t``: a look)."""
    p = select.poll()
    p.register(fd, events)
    left = t - _now()
    try:
        return bool(p.poll(left * 1000.0 if left > 0 else 0))
    except OSError as exc:
        raise _Failed(ERRNO, exc.errno or 0, STAGE_READ) from None


class Exchanger:
    """One master exchange per call (`pyrtu.core.xfer.Exchanger`)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._last = 0.0
        self._reads = 0

    def _take(self, fd: int, readable: bool) -> bool:
        """Read what ``fd`` has; True when bytes came."""
        if len(self._buf) >= CAPACITY:
            return False
        try:
            got = os.read(fd, CAPACITY - len(self._buf))
        except OSError as exc:
            if exc.errno in _AGAIN:
                return False
            raise _Failed(ERRNO, exc.errno or 0, STAGE_READ) from None
        if got:
            self._buf += got
            self._reads += 1
            self._last = _now()
            return True
        if readable:  # poll said input, read says end of file: the device is gone
            raise _Failed(GONE)
        return False

    def run(
        self,
        fd: int,
        drain: bool,
        request: bytes,
        send_at: float,
        first_wake: float,
        timeout: float,
        char: float,
        expect: int,
        short_len: int,
    ) -> XferResult:
        check_plan(request, first_wake, timeout, char, expect, short_len)
        if fd < 0:
            raise ValueError(f"fd must be an open descriptor, not {fd}")
        self._buf = bytearray()
        self._last = 0.0
        self._reads = 0
        state = [SHORT, False, 0.0, 0.0, 0, 0.0]  # status, sent, start, end, first_n, first_t
        err = stage = 0
        try:
            self._steps(
                fd, drain, request, send_at, first_wake, timeout, char, expect, short_len, state
            )
        except _Failed as f:
            state[0], err, stage = f.status, f.err, f.stage
        status, sent, start, end, first_n, first_t = state
        return XferResult(
            int(status),
            bool(sent),
            float(start),
            float(end),
            bytes(self._buf),
            int(first_n),
            float(first_t),
            self._last,
            err,
            stage,
            self._reads,
        )

    def _wanted(self, expect: int, short_len: int) -> int:
        buf = self._buf
        if short_len and len(buf) >= 2 and buf[1] & 0x80:
            return short_len
        return expect

    def _steps(
        self,
        fd: int,
        drain: bool,
        request: bytes,
        send_at: float,
        first_wake: float,
        timeout: float,
        char: float,
        expect: int,
        short_len: int,
        state: list[float | int | bool],
    ) -> None:
        _sleep_until(send_at)
        if _wait_fd(fd, select.POLLIN, 0.0) and self._take(fd, True):
            state[0] = STALE
            return
        start = _now()
        view = memoryview(request)
        limit = start + 1.0 + 2 * len(request) * char
        while view:
            try:
                view = view[os.write(fd, view) :]
                continue
            except OSError as exc:
                if exc.errno not in _AGAIN:
                    raise _Failed(ERRNO, exc.errno or 0, STAGE_WRITE) from None
            if _now() >= limit:
                raise _Failed(ERRNO, errno.ETIMEDOUT, STAGE_WRITE)
            _wait_fd(fd, select.POLLOUT, limit)
        if drain:
            try:
                termios.tcdrain(fd)
            except termios.error as exc:
                raise _Failed(ERRNO, exc.args[0], STAGE_WRITE) from None
        end = _now()
        if drain:
            end = max(end, start + len(request) * char)
        state[1:4] = [True, start, end]
        deadline = end + timeout
        _sleep_until(end + first_wake)
        self._take(fd, False)
        state[4:6] = [len(self._buf), self._last]
        while len(self._buf) < self._wanted(expect, short_len):
            left = self._wanted(expect, short_len) - len(self._buf)
            got = False
            if self._buf and left > 1:
                _sleep_until(min(self._last + (left - 1) * char, deadline))
                got = self._take(fd, False)
            if not got:
                if not _wait_fd(fd, select.POLLIN, deadline):
                    return  # the deadline
                self._take(fd, True)
            if not state[4]:
                state[4:6] = [len(self._buf), self._last]
        state[0] = ANSWER


class AsyncExchanger:
    """The twin of rtu_xfer_worker: exchanges on a thread of their own, for an event
    loop; `submit`, then watch `fd`; `result` once it is readable."""

    def __init__(self) -> None:
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self.fd, self._w = r, w
        self._ex = Exchanger()
        self._cv = threading.Condition()
        self._job: tuple[Any, ...] | None = None
        self._busy = False
        self._closed = False
        self._report: XferResult | None = None
        self._thread = threading.Thread(target=self._main, name="pyrtu-exchange", daemon=True)
        self._thread.start()

    def _main(self) -> None:
        while True:
            with self._cv:
                while self._job is None and not self._closed:
                    self._cv.wait()
                job, self._job = self._job, None
                if job is None:
                    return
            report = self._ex.run(*job)
            with self._cv:
                self._report, self._busy = report, False
            try:
                os.write(self._w, b"\x01")
            except BlockingIOError:  # a full pipe already holds a wake-up
                pass

    def submit(
        self,
        fd: int,
        drain: bool,
        request: bytes,
        send_at: float,
        first_wake: float,
        timeout: float,
        char: float,
        expect: int,
        short_len: int,
    ) -> None:
        check_plan(request, first_wake, timeout, char, expect, short_len)
        if fd < 0:
            raise ValueError(f"fd must be an open descriptor, not {fd}")
        with self._cv:
            if self._closed:
                raise ValueError("this exchanger is closed")
            if self._busy:
                raise RuntimeError("an exchange is under way")
            self._busy = True
            self._job = (fd, drain, request, send_at, first_wake, timeout, char, expect, short_len)
            self._cv.notify()

    def result(self) -> XferResult | None:
        """The exchange's report once it is over (`fd` readable), else None."""
        try:
            os.read(self.fd, 64)
        except BlockingIOError:
            pass
        with self._cv:
            if self._busy:
                return None
            return self._report  # (the last exchange's, until the next one)

    def close(self) -> None:
        """End the thread (after the exchange under way, if any)."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            self._cv.notify()
        self._thread.join()
        os.close(self.fd)
        os.close(self._w)
