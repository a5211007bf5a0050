"""The mux in C (csrc/rtu_mux_io.c; `pyrtu.tcp.mux` has the contract,
pyrtu/tcp/_pymux.py the twin).  Imported by `pyrtu.tcp.mux` only for the C
backend (the extension is built then)."""

from __future__ import annotations

import os
import socket

from pyrtu.core._rtu_core import ffi, lib
from pyrtu.tcp.mux import MuxDone, MuxError, refused

_NONE = 2**63 - 1


def supported() -> bool:
    """Whether the C core has a mux here (epoll: Linux)."""
    return hasattr(lib, "rtu_mux_size") and lib.rtu_mux_size(1) > 0


class CMux:
    """`pyrtu.tcp.mux.TcpMux` over csrc/rtu_mux_io.c."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._mem = ffi.new("char[]", lib.rtu_mux_size(capacity))
        self._m = ffi.cast("rtu_mux *", self._mem)
        if lib.rtu_mux_init(self._m, capacity) != 0:
            err = lib.rtu_mux_errno(self._m)
            raise MuxError(err, f"the mux cannot start: {os.strerror(err)}")
        self._out = ffi.new("rtu_mux_done[]", capacity)
        self._socks: dict[int, socket.socket] = {}
        self._free = list(range(capacity - 1, -1, -1))
        self._closed = False

    @property
    def fd(self) -> int:
        return int(lib.rtu_mux_fd(self._m))

    def attach(self, sock: socket.socket) -> int:
        if not self._free:
            raise ValueError(f"all {self.capacity} connections of the mux are attached")
        sock.setblocking(False)
        conn = self._free.pop()
        if lib.rtu_mux_attach(self._m, conn, sock.fileno()) != 0:
            self._free.append(conn)
            raise ValueError(f"the mux refused {sock!r}")
        self._socks[conn] = sock
        return conn

    def detach(self, conn: int) -> None:
        sock = self._socks.pop(conn, None)
        if sock is None:
            return
        lib.rtu_mux_detach(self._m, conn)
        self._free.append(conn)
        sock.close()

    def submit(
        self,
        conn: int,
        token: int,
        tid: int,
        unit: int,
        pdu: bytes,
        timeout: float,
        awaited: bool = True,
    ) -> bool:
        if not (0 <= token < 2**64 and 0 <= conn < 2**32 and 0 <= tid <= 0xFFFF
                and 0 <= unit <= 0xFF and 0 <= timeout < 9e9):  # fmt: skip
            rc = -1  # (what C would refuse, refused before cffi's own conversions)
        else:
            rc = lib.rtu_mux_submit(
                self._m, conn, token, tid, unit, pdu, len(pdu), awaited, int(timeout * 1e9)
            )
        if rc not in (0, 1):
            raise refused(conn, tid, unit, pdu, timeout)
        return rc == 1

    def service(self) -> int:
        n = lib.rtu_mux_service(self._m)
        if n < 0:
            err = lib.rtu_mux_errno(self._m)
            raise MuxError(err, f"the mux's epoll failed: {os.strerror(err)}")
        return int(n)

    def deadline(self) -> float | None:
        t = lib.rtu_mux_deadline(self._m)
        return None if t == _NONE else t * 1e-9

    def take(self) -> list[MuxDone]:
        out = self._out
        n = lib.rtu_mux_take(self._m, out, self.capacity)
        done = []
        buf = ffi.buffer
        for i in range(n):
            d = out[i]
            done.append(MuxDone(d.token, d.conn, d.status, d.err, d.stage, d.late, d.tid,
                                d.start * 1e-9, d.end * 1e-9, buf(d.adu, d.len)[:]))  # fmt: skip
        return done

    @property
    def services(self) -> int:
        return int(lib.rtu_mux_services(self._m))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for conn in list(self._socks):
            self.detach(conn)
        lib.rtu_mux_destroy(self._m)


__all__ = ["CMux", "supported"]
