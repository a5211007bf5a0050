"""The xfer runners of a backend: C (pyrtu/drivers/_cxfer.py over csrc/rtu_xfer_io.c)
for the C core, the twin (pyrtu/drivers/_pyxfer.py) for the pure-Python one; the
contract is `pyrtu.drivers.xfer`.  Each master or slave asks once, for its own
backend (``backend=`` of the constructors)."""

from __future__ import annotations

import socket
from collections.abc import Callable
from types import ModuleType
from typing import Any

from pyrtu.drivers.xfer import AsyncXferRunner, TcpScanner, TcpXferRunner, XferRunner


def _impl(backend: ModuleType) -> ModuleType:
    # the C xfer needs the core's POSIX I/O (not built on Windows: POSIX_IO)
    if getattr(backend, "BACKEND", "python") == "c" and getattr(backend, "POSIX_IO", False):
        from pyrtu.drivers import _cxfer

        return _cxfer
    from pyrtu.drivers import _pyxfer

    return _pyxfer


def xfer_runner(backend: ModuleType) -> XferRunner:
    """A new `XferRunner` of ``backend``'s kind (a `pyrtu.core._backend` module)."""
    ex: XferRunner = _impl(backend).XferRunner()
    return ex


def async_xfer_runner(backend: ModuleType) -> AsyncXferRunner:
    """A new `AsyncXferRunner` of ``backend``'s kind: its thread starts now."""
    ax: AsyncXferRunner = _impl(backend).AsyncXferRunner()
    return ax


def tcp_xfer_runner(
    backend: ModuleType,
    sock: socket.socket,
    io: Any = None,
    why: Callable[[], str] | None = None,
) -> TcpXferRunner:
    """A new `TcpXferRunner` of ``backend``'s kind on the connected, non-blocking
    ``sock`` (C: csrc/rtu_tcp_io.c on its descriptor; ``io``: a C layer on it, the
    TLS of `pyrtu.core._tls.CTlsConnection.io`, C only, and ``why`` its words for
    an error of its own, `TcpXferReport.why`)."""
    if io is not None:
        from pyrtu.drivers import _cxfer

        runner: TcpXferRunner = _cxfer.TcpXferRunner(sock, io, why)
        return runner
    runner = _impl(backend).TcpXferRunner(sock)
    return runner


def tcp_scanner(backend: ModuleType) -> TcpScanner:
    """A new `TcpScanner` of ``backend``'s kind (an event loop's TCP client's)."""
    scanner: TcpScanner = _impl(backend).TcpScanner()
    return scanner


__all__ = ["async_xfer_runner", "tcp_scanner", "tcp_xfer_runner", "xfer_runner"]
