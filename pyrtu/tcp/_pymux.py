"""The twin of csrc/rtu_mux_io.c (`pyrtu.tcp.mux` has the contract): `PyMux`
does the same with a selector whose descriptor the event loop watches, where the
C core has no mux (no epoll) or the pure-Python backend runs."""

from __future__ import annotations

import errno
import heapq
import platform
import selectors
import socket
import struct
import sys
import time

from pyrtu.drivers._pyxfer import tcp_scan
from pyrtu.drivers.xfer import (
    STAGE_RECEIVE,
    STAGE_SEND,
    TCP_ANSWER,
    TCP_BAD_HEADER,
    TCP_CLOSED,
    TCP_ERRNO,
    TCP_EXCEPTION,
    TCP_MISMATCH,
    TCP_TIMEOUT,
    TcpScan,
)
from pyrtu.tcp.mux import REPEATING, RESENT, MuxDone, MuxError, refused, refused_repeat


def supported() -> bool:
    """Whether the selector here has a descriptor of its own (epoll, kqueue)."""
    sel = selectors.DefaultSelector()
    try:
        return callable(getattr(sel, "fileno", None))
    finally:
        sel.close()


_MBAP = struct.Struct(">HHHB")
#: Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS; asm-generic, x86 and arm: Python's
#: socket module does not name it): the kernel's time of each read, as the C mux
#: takes it; elsewhere the time of the read
_TIMESTAMPNS = 35 if sys.platform == "linux" and platform.machine() in (
    "x86_64", "aarch64", "armv7l", "i686", "riscv64") else None  # fmt: skip
_TIMESPEC = struct.Struct("@qq")
_BUF_CAP = 520  # csrc/rtu_tcp.h RTU_TCP_MIN_CAP: two whole ADUs
_MAX_ADU = 260
_MAX_INTERVAL = 2**60  # ns: csrc/rtu_mux_io.c MAX_INTERVAL


class _Conn:
    __slots__ = (
        "awaited",
        "broken",
        "broken_err",
        "buf",
        "busy",
        "deadline",
        "fc",
        "gen",
        "interval",
        "late",
        "queued",
        "repeat",
        "req",
        "req_len",
        "request",
        "resent",
        "sock",
        "start",
        "tid",
        "timeout",
        "token",
        "unit",
        "used",
    )  # fmt: skip

    def __init__(self, sock: socket.socket, gen: int) -> None:
        self.sock = sock
        self.gen = gen
        self.busy = self.queued = False
        self.broken = self.broken_err = 0
        self.tid = self.unit = self.fc = self.token = 0
        self.start = self.deadline = 0.0
        self.req = b""  # what is still to be sent of the request
        self.req_len = 0
        self.request = b""  # the request ADU, its transaction id to be set
        self.timeout = 0.0
        self.repeat = self.resent = False
        self.interval = 0.0
        self.awaited = True
        self.buf = bytearray()
        self.used = 0
        self.late = 0


class PyMux:
    """`pyrtu.tcp.mux.TcpMux` with a selector (see the module docstring)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._sel = selectors.DefaultSelector()
        self._conns: dict[int, _Conn] = {}
        self._gens = [0] * capacity
        self._free = list(range(capacity - 1, -1, -1))
        self._done: list[MuxDone] = []
        self._deadlines: list[tuple[float, int, int, int]] = []  # (deadline, seq, conn, gen)
        self._due: dict[int, float] = {}  # each repeating connection's next send
        self._seq = 0
        self._services = 0
        self._closed = False

    @property
    def fd(self) -> int:
        return int(self._sel.fileno())

    # ------------------------------------------------------------ the caller's side

    def attach(self, sock: socket.socket) -> int:
        if not self._free:
            raise ValueError(f"all {self.capacity} connections of the mux are attached")
        sock.setblocking(False)
        if _TIMESTAMPNS is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, _TIMESTAMPNS, 1)
            except OSError:  # (an optimisation only)
                pass
        conn = self._free.pop()
        self._gens[conn] += 1
        self._conns[conn] = _Conn(sock, self._gens[conn])
        self._sel.register(sock, selectors.EVENT_READ, conn)
        return conn

    def detach(self, conn: int) -> None:
        k = self._conns.pop(conn, None)
        if k is None:
            return
        self._unwatch(k)
        self._due.pop(conn, None)
        self._gens[conn] += 1
        self._done = [d for d in self._done if d.conn != conn]
        self._free.append(conn)
        k.sock.close()

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
        k = self._conns.get(conn)
        # (a NaN timeout is refused: no comparison holds for it)
        if (k is None or k.busy or k.queued or not 0 <= token < 2**64 or not 0 <= tid <= 0xFFFF
                or not 0 <= unit <= 0xFF or not 1 <= len(pdu) <= 253
                or not timeout >= 0):  # fmt: skip
            raise refused(conn, tid, unit, pdu, timeout)
        self._unrepeat(conn, k)  # (a request of its own: a repeat of another ends)
        k.token, k.unit, k.fc = token, unit, pdu[0]
        k.timeout, k.awaited = timeout, awaited
        k.request = _MBAP.pack(tid, 0, len(pdu) + 1, unit) + pdu
        k.req_len = len(k.request)
        k.resent = False
        return self._begin(conn, k, tid, time.monotonic())

    def repeat(self, conn: int, first: float, interval: float) -> None:
        k = self._conns.get(conn)
        # (the C mux's checks, its interval in nanoseconds, and CMux's bounds on
        # ``first``; NaN fails them)
        if (k is None or not k.req_len or not k.awaited or k.queued or not -9e9 < first < 9e9
                or not 1 <= interval * 1e9 <= _MAX_INTERVAL):  # fmt: skip
            raise refused_repeat(conn, first, interval)
        k.repeat, k.interval = True, interval
        self._due[conn] = first

    def unrepeat(self, conn: int) -> bool:
        k = self._conns.get(conn)
        if k is None:
            raise ValueError(f"connection {conn} of the mux is not attached")
        self._unrepeat(conn, k)
        return k.busy or k.queued

    def service(self) -> int:
        self._services += 1
        try:
            events = self._sel.select(0)
        except OSError as exc:
            raise MuxError(exc.errno or 0, f"the mux's selector failed: {exc}") from exc
        now = time.monotonic()
        for key, mask in events:
            conn = key.data
            k = self._conns.get(conn)
            if k is None or k.sock is not key.fileobj:
                continue
            if mask & selectors.EVENT_WRITE and k.busy and k.req:
                self._transmit(conn, k, now)
            if mask & selectors.EVENT_READ and k.broken == 0:
                self._receive(conn, k, now)
        now = time.monotonic()
        self._expire(now)
        self._resend(now)
        return len(self._done)

    def deadline(self) -> float | None:
        first = self._first()
        at = None if first is None else first[1].deadline
        conns = self._conns
        for conn, due in self._due.items():
            if (at is None or due < at) and not conns[conn].busy:
                at = due
        return at

    def take(self) -> list[MuxDone]:
        out, self._done = self._done, []
        conns = self._conns
        for i, d in enumerate(out):
            k = conns[d.conn]
            k.queued = False
            if k.repeat:
                out[i] = d._replace(flags=d.flags | REPEATING)
        return out

    @property
    def services(self) -> int:
        return self._services

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for conn in list(self._conns):
            self.detach(conn)
        self._sel.close()

    # ------------------------------------------------------------ the steps

    def _begin(self, conn: int, k: _Conn, tid: int, now: float) -> bool:
        """Send ``k``'s request (``k.request``) as transaction ``tid``; whether it
        ended already (its record waits)."""
        del k.buf[: k.used]
        k.used = 0
        k.tid = tid
        k.start, k.deadline = now, now + k.timeout
        k.busy = True
        self._seq += 1
        heapq.heappush(self._deadlines, (k.deadline, self._seq, conn, k.gen))
        if k.broken:  # it failed while idle: nothing is sent
            self._finish(conn, k, k.broken, k.broken_err, STAGE_RECEIVE, b"", now)
            return True
        k.req = tid.to_bytes(2, "big") + k.request[2:]
        self._transmit(conn, k, now)
        if k.busy:
            self._scan(conn, k, now)
        return not k.busy

    def _unrepeat(self, conn: int, k: _Conn) -> None:
        k.repeat = False
        self._due.pop(conn, None)

    def _resend(self, now: float) -> None:
        """The repeats due by ``now`` of the idle connections sent."""
        for conn, due in list(self._due.items()):
            k = self._conns[conn]
            if due > now or k.busy or k.queued:
                continue
            # its beat: one interval on from when it was due, or from now when that
            # is more than an interval behind
            nxt = due + k.interval
            self._due[conn] = nxt if nxt >= now - k.interval else now
            k.resent = True
            self._begin(conn, k, (k.tid + 1) & 0xFFFF, now)

    def _unwatch(self, k: _Conn) -> None:
        try:
            self._sel.unregister(k.sock)
        except (KeyError, ValueError):
            pass

    def _finish(self, conn: int, k: _Conn, status: int, err: int, stage: int, adu: bytes,
                end: float) -> None:  # fmt: skip
        k.busy = False
        if k.queued:
            return
        flags = RESENT if k.resent else 0
        if k.repeat and (status != TCP_ANSWER or err or k.late or not adu):
            self._unrepeat(conn, k)  # (only a plain answer keeps it going)
        self._done.append(MuxDone(k.token, conn, status, err, stage, k.late, k.tid, k.start,
                                  end, adu, flags))  # fmt: skip
        k.late = 0
        k.queued = True

    def _lost(self, k: _Conn, status: int, err: int) -> None:
        k.broken, k.broken_err = status, err
        self._unwatch(k)

    def _scan(self, conn: int, k: _Conn, now: float) -> None:
        s = tcp_scan(k.buf, len(k.buf), k.tid if k.busy else 0x10000, TcpScan(k.used))
        k.used = s.used
        if not k.busy:  # idle: whatever is whole is late
            k.late += s.late + (s.ans_len != 0)
            if s.error:
                self._lost(k, TCP_BAD_HEADER, s.error)
            return
        k.late += s.late - s.late_after
        if s.ans_len:
            adu = bytes(k.buf[s.ans_off + 6 : s.ans_off + s.ans_len])
            status = TCP_ANSWER
            if adu[0] != k.unit or adu[1] & 0x7F != k.fc:
                status = TCP_MISMATCH
            elif adu[1] & 0x80:
                status = TCP_EXCEPTION
            self._finish(conn, k, status, s.error, 0, adu, now)
            k.late = s.late_after
            if s.error:  # after the answer: nothing more
                self._lost(k, TCP_BAD_HEADER, s.error)
        elif s.error:
            self._finish(conn, k, TCP_BAD_HEADER, s.error, 0, b"", now)
            self._lost(k, TCP_BAD_HEADER, s.error)

    def _transmit(self, conn: int, k: _Conn, now: float) -> None:
        while k.req:
            try:
                w = k.sock.send(k.req)
            except (BlockingIOError, InterruptedError):
                self._sel.modify(k.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, conn)
                return
            except OSError as exc:
                err = exc.errno or errno.EPIPE
                self._finish(conn, k, TCP_ERRNO, err, STAGE_SEND, b"", now)
                self._lost(k, TCP_ERRNO, err)
                return
            k.req = k.req[w:]
        try:
            self._sel.modify(k.sock, selectors.EVENT_READ, conn)
        except (KeyError, ValueError):
            pass
        if not k.awaited:  # a broadcast: nothing comes back
            self._finish(conn, k, TCP_ANSWER, 0, 0, b"", now)

    def _receive(self, conn: int, k: _Conn, now: float) -> None:
        if _BUF_CAP - len(k.buf) < _MAX_ADU:
            del k.buf[: k.used]
            k.used = 0
        try:
            got, ancillary, _, _ = k.sock.recvmsg(_BUF_CAP - len(k.buf), 64)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            err = exc.errno or errno.EIO
            if k.busy:
                self._finish(conn, k, TCP_ERRNO, err, STAGE_RECEIVE, b"", now)
            self._lost(k, TCP_ERRNO, err)
            return
        if not got:
            if k.busy:
                self._finish(conn, k, TCP_CLOSED, 0, STAGE_RECEIVE, b"", now)
            self._lost(k, TCP_CLOSED, 0)
            return
        k.buf += got
        arrived = now
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == _TIMESTAMPNS and len(data) >= 16:
                sec, nsec = _TIMESPEC.unpack_from(data)
                arrived = sec + nsec * 1e-9 + (time.monotonic() - time.time())
                if not k.start <= arrived <= now:
                    arrived = now  # (the realtime clock was stepped)
        self._scan(conn, k, arrived)

    def _first(self) -> tuple[int, _Conn] | None:
        """The transaction in flight due first (its connection), the stale entries
        before it dropped: a transaction ended since, a connection detached."""
        heap = self._deadlines
        while heap:
            deadline, _, conn, gen = heap[0]
            k = self._conns.get(conn)
            if k is not None and k.gen == gen and k.busy and k.deadline == deadline:
                return conn, k
            heapq.heappop(heap)
        return None

    def _expire(self, now: float) -> None:
        while (first := self._first()) is not None and first[1].deadline <= now:
            conn, k = first
            heapq.heappop(self._deadlines)
            self._finish(conn, k, TCP_TIMEOUT, 0, 0, b"", now)
            if 0 < len(k.req) < k.req_len:
                # part of the request is on the wire: the stream cannot carry another
                self._lost(k, TCP_ERRNO, errno.ETIMEDOUT)
            elif k.req:  # none of it went out: it never will
                k.req = b""
                self._sel.modify(k.sock, selectors.EVENT_READ, conn)


__all__ = ["PyMux"]
