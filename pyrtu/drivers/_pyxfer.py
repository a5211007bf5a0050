"""The twin of csrc/rtu_xfer_io.c: one master xfer on a serial descriptor, in
Python (`pyrtu.drivers.xfer` has the contract; pyrtu/drivers/_cxfer.py the C one).
Step for step as the C file: sleep to the send time, look for stale input, write
(tcdrain on a real line), sleep to the first read, then sleep through all but the
last character and wait for it; a readable cancel descriptor ends it
(`AsyncXferRunner.cancel`)."""

from __future__ import annotations

import errno
import os
import select
import threading
import time

from pyrtu.drivers._pipes import drain, poke
from pyrtu.drivers.xfer import (
    ANSWER,
    CANCELLED,
    CAPACITY,
    ERRNO,
    GONE,
    SHORT,
    STAGE_READ,
    STAGE_WRITE,
    STALE,
    XferPlan,
    XferResult,
    check_plan,
)

_now = time.monotonic
_AGAIN = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR)


class _Failed(Exception):
    """A step ended the xfer (status, err, stage)."""

    def __init__(self, status: int, err: int = 0, stage: int = 0) -> None:
        super().__init__(status)
        self.status, self.err, self.stage = status, err, stage


def _wait_fd(fd: int, events: int, t: float, cancel: int = -1) -> bool:
    """``events`` on ``fd`` before ``t`` (a past ``t``: a look); `_Failed` CANCELLED
    when ``cancel`` becomes readable first."""
    p = select.poll()
    p.register(fd, events)
    if cancel >= 0:
        p.register(cancel, select.POLLIN)
    left = t - _now()
    try:
        ready = p.poll(left * 1000.0 if left > 0 else 0)
    except OSError as exc:
        raise _Failed(ERRNO, exc.errno or 0, STAGE_READ) from None
    if any(fd_ == cancel for fd_, _ in ready):
        raise _Failed(CANCELLED)
    return bool(ready)


def _pause_until(t: float, cancel: int) -> None:
    """Sleep until ``t``, watching only ``cancel`` (-1: none)."""
    if cancel < 0:
        left = t - _now()
        if left > 0:
            time.sleep(left)
        return
    while _now() < t:
        p = select.poll()
        p.register(cancel, select.POLLIN)
        if p.poll(max(0.0, (t - _now()) * 1000.0)):
            raise _Failed(CANCELLED)


class XferRunner:
    """One master xfer per call (`pyrtu.drivers.xfer.XferRunner`)."""

    def __init__(self, cancel_fd: int = -1) -> None:
        self._buf = bytearray()
        self._last = 0.0
        self._reads = 0
        self._cancel = cancel_fd

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

    def run(self, plan: XferPlan) -> XferResult:
        check_plan(plan)
        self._buf = bytearray()
        self._last = 0.0
        self._reads = 0
        state = [SHORT, False, 0.0, 0.0, 0, 0.0]  # status, sent, start, end, first_n, first_t
        err = stage = 0
        try:
            self._steps(plan, state)
        except _Failed as f:
            state[0], err, stage = f.status, f.err, f.stage
        status, sent, start, end, first_n, first_t = state
        return XferResult(int(status), bool(sent), float(start), float(end), bytes(self._buf),
                          int(first_n), float(first_t), self._last, err, stage,
                          self._reads)  # fmt: skip

    def _wanted(self, expect: int, short_len: int) -> int:
        buf = self._buf
        if short_len and len(buf) >= 2 and buf[1] & 0x80:
            return short_len
        return expect

    def _transmit(self, fd: int, drain: bool, request: bytes, char: float,
                  state: list[float | int | bool]) -> float:  # fmt: skip
        """Step 3: the request on the line; the end of transmission."""
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
            import termios  # (POSIX only: a drained line is a real serial port)

            try:
                termios.tcdrain(fd)
            except termios.error as exc:
                raise _Failed(ERRNO, exc.args[0], STAGE_WRITE) from None
        end = _now()
        if drain:
            end = max(end, start + len(request) * char)
        state[1:4] = [True, start, end]
        return end

    def _steps(self, plan: XferPlan, state: list[float | int | bool]) -> None:
        fd, ex = plan.fd, plan.xfer
        expect, short_len = ex.expect, ex.short_len
        cancel = self._cancel
        _pause_until(ex.send_at - plan.spin, cancel)
        left = ex.send_at - _now()
        while left > 0:  # the last `spin` seconds on the clock (see XferPlan.spin)
            left = ex.send_at - _now()
        if plan.look and _wait_fd(fd, select.POLLIN, 0.0) and self._take(fd, True):
            state[0] = STALE
            return
        end = self._transmit(fd, plan.drain, ex.data, plan.char, state)
        if expect == 0:  # nothing awaited (a slave's response)
            state[0] = ANSWER
            return
        deadline = end + ex.timeout
        _pause_until(end + ex.first_wake, cancel)
        self._take(fd, False)
        state[4:6] = [len(self._buf), self._last]
        while len(self._buf) < self._wanted(expect, short_len):
            left = self._wanted(expect, short_len) - len(self._buf)
            got = False
            if self._buf and left > 1:
                _pause_until(min(self._last + (left - 1) * plan.char, deadline), cancel)
                got = self._take(fd, False)
            if not got:
                if not _wait_fd(fd, select.POLLIN, deadline, cancel):
                    return  # the deadline
                self._take(fd, True)
            if not state[4]:
                state[4:6] = [len(self._buf), self._last]
        state[0] = ANSWER


class AsyncXferRunner:
    """The twin of rtu_xfer_worker: xfers on a thread of their own, for an event
    loop; `submit`, then watch `fd`; `result` once it is readable; `cancel` ends the
    xfer under way."""

    def __init__(self) -> None:
        r, w = os.pipe()
        cr, cw = os.pipe()
        for fd in (r, w, cr, cw):
            os.set_blocking(fd, False)
        self.fd, self._w, self._cr, self._cw = r, w, cr, cw
        self._ex = XferRunner(cr)
        self._cv = threading.Condition()
        self._job: XferPlan | None = None
        self._busy = False
        self._closed = False
        self._report: XferResult | None = None
        self._thread = threading.Thread(target=self._main, name="pyrtu-xfer", daemon=True)
        self._thread.start()

    def _main(self) -> None:
        while True:
            with self._cv:
                while self._job is None and not self._closed:
                    self._cv.wait()
                job, self._job = self._job, None
                if job is None:
                    return
            report = self._ex.run(job)
            with self._cv:
                self._report, self._busy = report, False
            poke(self._w)

    def submit(self, plan: XferPlan) -> None:
        check_plan(plan)
        with self._cv:
            if self._closed:
                raise ValueError("this xfer runner is closed")
            if self._busy:
                raise RuntimeError("an xfer is under way")
            drain(self._cr)  # an old cancel
            self._busy = True
            self._job = plan
            self._cv.notify()

    def result(self) -> XferResult | None:
        """The report of the last xfer (None: one is under way)."""
        drain(self.fd)
        with self._cv:
            if self._busy:
                return None
            return self._report  # (the last xfer's, until the next one)

    def cancel(self) -> None:
        """End the xfer under way (before its write if that is not due yet); its
        report still comes (status CANCELLED)."""
        poke(self._cw)

    def close(self) -> None:
        """End the thread (the xfer under way is cancelled first)."""
        with self._cv:
            if self._closed:
                return
            self._closed = True
            self._cv.notify()
        self.cancel()
        self._thread.join()
        for fd in (self.fd, self._w, self._cr, self._cw):
            os.close(fd)
