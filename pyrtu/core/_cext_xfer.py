"""The C backend's exchange step (csrc/rtu_xfer_io.c; `pyrtu.core.xfer` has the
contract, pyrtu/core/_pure/xfer.py the twin): `Exchanger` runs one exchange per call
(the GIL released), `AsyncExchanger` on a C thread of its own for an event loop.
Re-exported by pyrtu/core/_cext.py."""

from __future__ import annotations

import math
import os
import weakref
from typing import Any

from pyrtu.core._rtu_core import ffi, lib
from pyrtu.core.xfer import CAPACITY, XferResult, check_plan


def _plan(
    x: Any,
    fd: int,
    drain: bool,
    request: bytes,
    send_at: float,
    first_wake: float,
    timeout: float,
    char: float,
    expect: int,
    short_len: int,
) -> Any:
    """Fill ``x`` (an rtu_xfer) for one exchange; the request's C view (keep it alive)."""
    check_plan(request, first_wake, timeout, char, expect, short_len)
    if fd < 0:
        raise ValueError(f"fd must be an open descriptor, not {fd}")
    req = ffi.from_buffer("uint8_t[]", request)
    x.fd, x.drain, x.req, x.req_len = fd, drain, req, len(request)
    x.send_at = math.ceil(send_at * 1e9)  # never before it
    x.first_wake, x.timeout_ns = int(first_wake * 1e9), int(timeout * 1e9)
    x.char_ns, x.expect, x.short_len = max(1, int(char * 1e9)), expect, short_len
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


class Exchanger:
    """One master exchange per call, in C (csrc/rtu_xfer_io.c; `pyrtu.core.xfer`)."""

    def __init__(self) -> None:
        self._x = ffi.new("rtu_xfer *")
        self._buf = ffi.new("uint8_t[]", CAPACITY)
        self._x.buf = self._buf
        self._x.cap = CAPACITY

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
        x = self._x
        _req = _plan(x, fd, drain, request, send_at, first_wake, timeout, char, expect, short_len)
        if lib.rtu_xfer_io_run(x) != lib.RTU_OK:
            raise ValueError(f"fd must be an open descriptor, not {fd}")
        return _report(x, self._buf)


def _stop_worker(worker: Any, x: Any, buf: Any, fds: tuple[int, int]) -> None:
    """End the worker's thread (after its exchange under way), then free its pipe;
    holds ``x`` and ``buf`` until the thread is gone."""
    lib.rtu_xfer_worker_stop(worker)
    for fd in fds:
        os.close(fd)


class AsyncExchanger:
    """Exchanges on a C thread of their own, for an event loop
    (`pyrtu.core.xfer.AsyncExchanger`): `submit`, then watch `fd`; `result` once it
    is readable."""

    def __init__(self) -> None:
        self._x = ffi.new("rtu_xfer *")
        self._buf = ffi.new("uint8_t[]", CAPACITY)
        self._x.buf = self._buf
        self._x.cap = CAPACITY
        self._req: Any = None
        r, w = os.pipe()
        os.set_blocking(r, False)
        os.set_blocking(w, False)
        self.fd = r
        self._worker = ffi.new("char[]", lib.rtu_xfer_worker_size())
        worker = ffi.cast("rtu_xfer_worker *", self._worker)
        if lib.rtu_xfer_worker_start(worker, self._x, w) != lib.RTU_OK:
            os.close(r)
            os.close(w)
            raise OSError("pyrtu: the exchange thread could not be started")
        self._w = worker
        self._stop = weakref.finalize(self, _stop_worker, worker, self._x, self._buf, (r, w))

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
        if not self._stop.alive:
            raise ValueError("this exchanger is closed")
        if lib.rtu_xfer_worker_rc(self._w) == lib.RTU_EBUSY:
            raise RuntimeError("an exchange is under way")
        self._req = _plan(
            self._x, fd, drain, request, send_at, first_wake, timeout, char, expect, short_len
        )
        lib.rtu_xfer_worker_submit(self._w)

    def result(self) -> XferResult | None:
        """The exchange's report once it is over (`fd` readable), else None."""
        try:
            os.read(self.fd, 64)
        except BlockingIOError:
            pass
        rc = lib.rtu_xfer_worker_rc(self._w)
        if rc == lib.RTU_EBUSY:
            return None
        self._req = None
        if rc != lib.RTU_OK:
            raise ValueError("fd must be an open descriptor")
        return _report(self._x, self._buf)

    def close(self) -> None:
        """End the thread (after the exchange under way, if any)."""
        self._stop()


__all__ = ["AsyncExchanger", "Exchanger"]
