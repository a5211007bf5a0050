"""The twin of csrc/rtu_xfer_io.c: one master xfer on a serial descriptor, in
Python (`pyrtu.drivers.xfer` has the contract; pyrtu/drivers/_cxfer.py the C one).
Step for step as the C file: sleep to the send time, look for stale input, write
(tcdrain on a real line), sleep to the first read, then sleep through all but the
last character and wait for it; a readable cancel descriptor ends it
(`AsyncXferRunner.cancel`).  `TcpXferRunner` is the twin of csrc/rtu_tcp_io.c (and
`tcp_scan` of csrc/rtu_tcp.c): a Modbus TCP client's transaction, step for step."""

from __future__ import annotations

import errno
import os
import select
import socket
import struct
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
    STAGE_RECEIVE,
    STAGE_SEND,
    STAGE_WRITE,
    STALE,
    TCP_ANSWER,
    TCP_BAD_HEADER,
    TCP_CAPACITY,
    TCP_CLOSED,
    TCP_ERRNO,
    TCP_EXCEPTION,
    TCP_MISMATCH,
    TCP_NOTE,
    TCP_TIMEOUT,
    TcpScan,
    TcpXferReport,
    XferPlan,
    XferResult,
    check_plan,
)

_now = time.monotonic
__all__ = ["AsyncXferRunner", "TcpScanner", "TcpXferRunner", "XferRunner", "tcp_scan"]
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


# ----------------------------------------------------------- Modbus TCP (rtu_tcp*.c)

_MBAP = struct.Struct(">HHH")  # transaction id, protocol id, length
_MBAP_MAX_ADU = 260
#: RTU_MBAP_ERR_* (pyrtu.core.mbap.MBAP_ERROR_BY_CODE)
_ERR_PROTOCOL, _ERR_LENGTH = 1, 2


def tcp_scan(buf: bytes | bytearray, n: int, tid: int, scan: TcpScan) -> TcpScan:
    """The twin of rtu_tcp_scan (csrc/rtu_tcp.c): ``buf[scan.used:n]`` scanned on
    for the answer to ``tid``; late ADUs counted; stops at a partial ADU or an
    invalid header (Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3)."""
    used, ans_off, ans_len, late, late_after, error = scan
    tid &= 0xFFFF
    while not error and used < n:
        left = n - used
        if left >= 4 and buf[used + 2] | buf[used + 3]:
            error = _ERR_PROTOCOL  # protocol id 0 = MODBUS
            break
        if left < 6:
            break
        length = buf[used + 4] << 8 | buf[used + 5]
        if not 2 <= length <= 254:
            error = _ERR_LENGTH  # unit id + a PDU of 1..253 bytes
            break
        if left < 6 + length:
            break
        if not ans_len and (buf[used] << 8 | buf[used + 1]) == tid:
            ans_off, ans_len = used, 6 + length
        else:
            late += 1  # it pairs with no request waiting
            if ans_len:
                late_after += 1
        used += 6 + length
    return TcpScan(used, ans_off, ans_len, late, late_after, error)


_NOTHING_SCANNED = TcpScan()


class TcpScanner:
    """`tcp_scan` over a receive buffer of its own (`pyrtu.drivers.xfer.TcpScanner`;
    the twin of pyrtu/drivers/_cxfer.py's)."""

    def __init__(self, capacity: int = TCP_CAPACITY) -> None:
        self.buf = bytearray(capacity)

    def scan(self, n: int, tid: int) -> TcpScan:
        return tcp_scan(self.buf, n, tid, _NOTHING_SCANNED)


class TcpXferRunner:
    """The twin of csrc/rtu_tcp_io.c (`pyrtu.drivers.xfer.TcpXferRunner`): on the
    non-blocking socket ``sock`` (the caller's)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self._buf = bytearray()
        self._scan = TcpScan()
        self._status = TCP_ANSWER
        self._err = self._stage = 0
        self._start = self._end = 0.0
        self._unit = self._fc = self._tid = 0
        self.answer = b""
        self._poller = select.poll()
        self._poller.register(sock, select.POLLIN)

    def call(self, tid: int, unit: int, pdu: bytes, awaited: bool, timeout: float) -> int:
        if not 0 <= tid <= 0xFFFF or not 0 <= unit <= 0xFF or not 1 <= len(pdu) <= 253:
            raise ValueError(f"bad TCP xfer arguments: tid {tid}, unit {unit}, pdu {pdu!r}")
        del self._buf[: self._scan.used]  # a partial ADU of an earlier answer stays
        self._scan = TcpScan()
        self._err = self._stage = 0
        self._end = 0.0
        self._tid, self._unit, self._fc = tid, unit, pdu[0]
        self.answer = b""
        self._start = _now()
        self._deadline = self._start + timeout
        status = self._transmit(_MBAP.pack(tid, 0, len(pdu) + 1) + bytes((unit,)) + pdu)
        if status is None:
            status = self._receive() if awaited else TCP_ANSWER
        return self._noted(status)

    def resume(self) -> int:
        return self._noted(self._receive())

    def _noted(self, status: int) -> int:
        """The word of `pyrtu.drivers.xfer.TCP_NOTE` (rtu_tcp_xfer_word)."""
        self._status = word = status
        scan = self._scan
        if scan.late or scan.error:
            word |= TCP_NOTE
        if scan.ans_len:
            self.answer = bytes(self._buf[scan.ans_off + 7 : scan.ans_off + scan.ans_len])
            word |= (scan.ans_len - 7) << 8
        return word

    def _failed(self, stage: int, exc: OSError) -> int:
        self._err, self._stage = exc.errno or 0, stage
        return TCP_ERRNO

    def _transmit(self, adu: bytes) -> int | None:
        """The request on the socket; None sent, else the status."""
        view = memoryview(adu)
        while view:
            try:
                view = view[self._sock.send(view) :]
                continue
            except BlockingIOError:
                pass
            except OSError as exc:
                return self._failed(STAGE_SEND, exc)
            left = self._deadline - _now()
            if left <= 0:
                return TCP_TIMEOUT  # no room for the request in time
            select.select((), (self._sock,), (), left)
        return None

    def _judged(self) -> int | None:
        """The scan of what the buffer holds: the status once it is over, else None."""
        buf = self._buf
        scan = self._scan = tcp_scan(buf, len(buf), self._tid, self._scan)
        if scan.ans_len:
            off = scan.ans_off
            if buf[off + 6] != self._unit or buf[off + 7] & 0x7F != self._fc:
                return TCP_MISMATCH
            return TCP_EXCEPTION if buf[off + 7] & 0x80 else TCP_ANSWER
        return TCP_BAD_HEADER if scan.error else None

    def _receive(self) -> int:
        done = self._judged()
        if done is not None:
            return done
        sock, buf, poller = self._sock, self._buf, self._poller
        while True:
            left = self._deadline - _now()
            if not poller.poll(left * 1000.0 if left > 0 else 0):
                return TCP_TIMEOUT
            if TCP_CAPACITY - len(buf) < _MBAP_MAX_ADU:
                del buf[: self._scan.used]  # full of late answers: the unresolved bytes only
                self._scan = self._scan._replace(used=0)
            try:
                got = sock.recv(TCP_CAPACITY - len(buf))
            except BlockingIOError:
                continue
            except OSError as exc:
                return self._failed(STAGE_RECEIVE, exc)
            if not got:
                return TCP_CLOSED  # poll said input, recv says the end
            buf += got
            self._end = _now()
            done = self._judged()
            if done is not None:
                return done

    def end(self) -> float:
        return self._end

    def report(self) -> TcpXferReport:
        return TcpXferReport(self._status, self._start, self._end, bytes(self._buf),
                             self._scan, self._err, self._stage)  # fmt: skip
