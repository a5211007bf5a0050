"""The mux in C (csrc/rtu_mux_io.c; `pyrtu.tcp.mux` has the contract,
pyrtu/tcp/_pymux.py the twin).  Imported by `pyrtu.tcp.mux` only for the C
backend (the extension is built then)."""

from __future__ import annotations

import os
import socket
import struct

from pyrtu.core._rtu_core import ffi, lib
from pyrtu.tcp.mux import MuxDone, MuxError, refused, refused_repeat

_NONE = 2**63 - 1

#: an rtu_mux_done record's fields as their bytes lie (csrc/rtu_mux.h), with
#: their `struct` codes; checked against the compiler's layout at import
_FIELDS = (("token", "Q"), ("conn", "I"), ("status", "i"), ("err", "i"), ("stage", "i"),
           ("late", "I"), ("tid", "I"), ("start", "q"), ("end", "q"), ("flags", "I"), ("len", "I"),
           ("adu", "254s"))  # fmt: skip
_RECORD = struct.Struct("=" + "".join(code for _, code in _FIELDS))


def _record_layout() -> int:
    """The record's size in an array (ImportError when `_RECORD` is not the
    compiler's layout: the extension and this module disagree)."""
    offset = 0
    for name, code in _FIELDS:
        if ffi.offsetof("rtu_mux_done", name) != offset:
            raise ImportError(f"rtu_mux_done.{name} is not at byte {offset}: rebuild pyrtu")
        offset += struct.calcsize("=" + code)
    size: int = ffi.sizeof("rtu_mux_done")
    if size < _RECORD.size:
        raise ImportError("rtu_mux_done is smaller than its fields: rebuild pyrtu")
    return size


_SIZE = _record_layout()


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
        # (a NaN timeout is refused: no comparison holds for it)
        if not (0 <= token < 2**64 and 0 <= conn < 2**32 and 0 <= tid <= 0xFFFF
                and 0 <= unit <= 0xFF and timeout >= 0):  # fmt: skip
            rc = -1  # (what C would refuse, refused before cffi's own conversions)
        else:
            ns = int(timeout * 1e9) if timeout < 9e9 else _NONE  # (9e9 s on: no deadline)
            rc = lib.rtu_mux_submit(self._m, conn, token, tid, unit, pdu, len(pdu), awaited, ns)
        if rc not in (0, 1):
            raise refused(conn, tid, unit, pdu, timeout)
        return rc == 1

    def repeat(self, conn: int, first: float, interval: float) -> None:
        # (what cffi cannot convert, refused before it: C refuses the rest; NaN fails)
        if not (0 <= conn < 2**32 and -9e9 < first < 9e9 and 0 < interval < 9e9):
            rc = -1
        else:
            rc = lib.rtu_mux_repeat(self._m, conn, int(first * 1e9), int(interval * 1e9))
        if rc != 0:
            raise refused_repeat(conn, first, interval)

    def unrepeat(self, conn: int) -> bool:
        rc = lib.rtu_mux_unrepeat(self._m, conn) if 0 <= conn < 2**32 else -1
        if rc < 0:
            raise ValueError(f"connection {conn} of the mux is not attached")
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
        n = lib.rtu_mux_take(self._m, self._out, self.capacity)
        if not n:
            return []
        raw = ffi.buffer(self._out, n * _SIZE)  # (one view of every record, unpacked whole)
        done = []
        unpack, size = _RECORD.unpack_from, _SIZE
        for i in range(n):
            token, conn, status, err, stage, late, tid, start, end, flags, length, adu = unpack(
                raw, i * size
            )
            done.append(MuxDone(token, conn, status, err, stage, late, tid, start * 1e-9,
                                end * 1e-9, adu[:length], flags))  # fmt: skip
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
