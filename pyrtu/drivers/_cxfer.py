"""The xfer step in C (csrc/rtu_xfer_io.c; `pyrtu.drivers.xfer` has the contract,
pyrtu/drivers/_pyxfer.py the twin): `XferRunner` runs one xfer per call (the GIL
released), `AsyncXferRunner` on a C thread of its own for an event loop;
`TcpXferRunner` a Modbus TCP client's transaction in one call (csrc/rtu_tcp_io.c).
Imported by `pyrtu.drivers.xfer_runners` only for the C backend (the extension is
built then)."""

from __future__ import annotations

import math
import os
import socket
import weakref
from collections.abc import Callable
from typing import Any

from pyrtu.core._rtu_core import ffi, lib
from pyrtu.drivers._pipes import drain, poke
from pyrtu.drivers.xfer import (
    CAPACITY,
    TCP_CAPACITY,
    TCP_ERRNO,
    TcpScan,
    TcpXferReport,
    XferPlan,
    XferResult,
    check_plan,
)


def _new_xfer(cancel_fd: int) -> tuple[Any, Any]:
    """An rtu_xfer with its read buffer (keep both alive as long as the C side may
    use them)."""
    x = ffi.new("rtu_xfer *")
    buf = ffi.new("uint8_t[]", CAPACITY)
    x.buf, x.cap, x.cancel_fd = buf, CAPACITY, cancel_fd
    return x, buf


def _plan(x: Any, plan: XferPlan) -> Any:
    """Fill ``x`` for one xfer; the request's C view (keep it alive until the
    xfer is over)."""
    check_plan(plan)
    ex = plan.xfer
    req = ffi.from_buffer("uint8_t[]", ex.data)
    x.fd, x.drain, x.look, x.req, x.req_len = plan.fd, plan.drain, plan.look, req, len(req)
    x.send_at = math.ceil(ex.send_at * 1e9)  # never before it
    x.spin_ns = int(plan.spin * 1e9)
    x.first_wake, x.timeout_ns = int(ex.first_wake * 1e9), int(ex.timeout * 1e9)
    x.char_ns = max(1, int(plan.char * 1e9))
    x.expect, x.short_len = ex.expect, ex.short_len
    return req


def _report(x: Any, buf: Any) -> XferResult:
    n = x.n
    return XferResult(
        x.status,
        bool(x.sent),
        x.start * 1e-9,
        x.end * 1e-9,
        ffi.buffer(buf, n)[:] if n else b"",
        x.first_n,
        x.first_t * 1e-9,
        x.last_t * 1e-9,
        x.err,
        x.stage,
        x.reads,
    )


class XferRunner:
    """One master xfer per call, in C (csrc/rtu_xfer_io.c; `pyrtu.drivers.xfer`)."""

    def __init__(self) -> None:
        self._x, self._buf = _new_xfer(-1)

    def run(self, plan: XferPlan) -> XferResult:
        x = self._x
        _req = _plan(x, plan)
        if lib.rtu_xfer_io_run(x) != lib.RTU_OK:
            raise ValueError(f"fd must be an open descriptor, not {plan.fd}")
        return _report(x, self._buf)


def _stop_worker(worker: Any, keep: tuple[Any, ...], fds: tuple[int, ...]) -> None:
    """Cancel the worker's xfer under way, end its thread, then free its pipes;
    ``keep`` (the rtu_xfer and its buffer) lives until the thread is gone."""
    poke(fds[3])
    lib.rtu_xfer_worker_stop(worker)
    for fd in fds:
        os.close(fd)


class AsyncXferRunner:
    """Xfers on a C thread of their own, for an event loop
    (`pyrtu.drivers.xfer.AsyncXferRunner`): `submit`, then watch `fd`; `result` once it
    is readable; `cancel`."""

    def __init__(self) -> None:
        r, w = os.pipe()
        cr, cw = os.pipe()
        for fd in (r, w, cr, cw):
            os.set_blocking(fd, False)
        self.fd, self._cr, self._cw = r, cr, cw
        self._x, self._buf = _new_xfer(cr)
        self._req: Any = None
        self._closed = self._poked = False
        self._worker = ffi.new("char[]", lib.rtu_xfer_worker_size())
        worker = ffi.cast("rtu_xfer_worker *", self._worker)
        if lib.rtu_xfer_worker_start(worker, self._x, w) != lib.RTU_OK:
            for fd in (r, w, cr, cw):
                os.close(fd)
            raise OSError("pyrtu: the xfer thread could not be started")
        self._w = worker
        keep = (self._x, self._buf, self._worker)
        self._stop = weakref.finalize(self, _stop_worker, worker, keep, (r, w, cr, cw))

    def submit(self, plan: XferPlan) -> None:
        if self._closed:
            raise ValueError("this xfer runner is closed")
        if lib.rtu_xfer_worker_rc(self._w) == lib.RTU_EBUSY:
            raise RuntimeError("an xfer is under way")
        self._req = _plan(self._x, plan)
        if self._poked:  # an old cancel
            self._poked = False
            drain(self._cr)
        lib.rtu_xfer_worker_submit(self._w)

    def result(self) -> XferResult | None:
        """The report of the last xfer (None: one is under way)."""
        drain(self.fd)
        rc = lib.rtu_xfer_worker_rc(self._w)
        if rc == lib.RTU_EBUSY:
            return None
        if rc != lib.RTU_OK:
            raise ValueError("fd must be an open descriptor")
        return _report(self._x, self._buf)

    def cancel(self) -> None:
        """End the xfer under way (its report still comes: CANCELLED)."""
        self._poked = True
        poke(self._cw)

    def close(self) -> None:
        """End the thread (the xfer under way, if any, cancelled)."""
        self._closed = True
        self._stop()


class TcpXferRunner:
    """A Modbus TCP client's transactions on a connected socket, in C
    (csrc/rtu_tcp_io.c; `pyrtu.drivers.xfer.TcpXferRunner`) on the non-blocking
    socket ``sock`` (the caller's: it closes it)."""

    def __init__(
        self, sock: socket.socket, io: Any = None, why: Callable[[], str] | None = None
    ) -> None:
        x = ffi.new("rtu_tcp_xfer *")
        self._keep = ffi.new("char[]", TCP_CAPACITY)  # (char: ffi.unpack gives bytes)
        x.fd, x.buf, x.cap = sock.fileno(), ffi.cast("uint8_t *", self._keep), TCP_CAPACITY
        if io is not None:  # a layer on the socket: mbaps://'s TLS (pyrtu/core/_tls.py)
            x.io = io
        self._why = why  # the layer's words for an error of its own (TLS: OpenSSL's)
        self._x = x
        self._call = lib.rtu_tcp_xfer_call
        self.answer = ffi.buffer(x.answer)

    def call(self, tid: int, unit: int, pdu: bytes, awaited: bool, timeout: float) -> int:
        word: int = self._call(self._x, tid, unit, pdu, len(pdu), awaited, int(timeout * 1e9))
        if word < 0:
            raise ValueError(f"bad TCP xfer arguments: tid {tid}, unit {unit}, pdu {pdu!r}")
        return word

    def resume(self) -> int:
        x = self._x
        x.send = 0
        if lib.rtu_tcp_xfer_run(x) != lib.RTU_OK:
            raise ValueError("bad TCP xfer state")
        return lib.rtu_tcp_xfer_word(x)  # type: ignore[no-any-return]

    def end(self) -> float:
        return self._x.end * 1e-9  # type: ignore[no-any-return]

    def report(self) -> TcpXferReport:
        x = self._x
        s = x.scan
        scan = TcpScan(s.used, s.ans_off, s.ans_len, s.late, s.late_after, s.error)
        data = ffi.unpack(self._keep, x.n) if x.n else b""
        why = self._why() if self._why is not None and x.status == TCP_ERRNO else ""
        return TcpXferReport(
            x.status, x.start * 1e-9, x.end * 1e-9, data, scan, x.err, x.stage, why
        )


class TcpScanner:
    """rtu_tcp_scan (csrc/rtu_tcp.c) over a receive buffer of its own
    (`pyrtu.drivers.xfer.TcpScanner`): one C call per scan, no copy."""

    def __init__(self, capacity: int = TCP_CAPACITY) -> None:
        self.buf = bytearray(capacity)
        self._c = ffi.from_buffer("uint8_t[]", self.buf)
        self._new = ffi.new
        self._scan = lib.rtu_tcp_scan

    def scan(self, n: int, tid: int) -> TcpScan:
        s = self._new("rtu_tcp_scan_result *")  # (zeroed: scanned from 0)
        self._scan(self._c, n, tid, s)
        return s  # type: ignore[no-any-return]


__all__ = ["AsyncXferRunner", "TcpScanner", "TcpXferRunner", "XferRunner"]
