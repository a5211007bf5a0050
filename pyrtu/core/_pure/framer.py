"""The sans-I/O framer in pure Python: the twin of csrc/rtu_framer.c.

Each byte gets an arrival time: bytes that arrive together at `now` are spread
back over the character time, never before the previous byte.  The silence
before a byte (arrival - one character - previous arrival) above t1.5, or of
t3.5 and more, is recorded as a mark (Modbus over Serial Line 2.5.1.1).
"""

from __future__ import annotations

from pyrtu.core._pure.head import (
    ACT_DISCARD,
    ACT_WAIT,
    INT64_MAX,
    KIND_DISCARD,
    MARK_T15,
    MARK_T35,
    ROLE_MASTER,
    Config,
    CoreState,
    View,
    head_needed,
    sat_add,
    sat_mul,
    sat_sub,
    time_clamp,
    try_head,
)

NO_TIME = None
FRAMER_CAP = 2 * 1024

# An event: (offset, length, kind, error, start_us, end_us, adu)
Event = tuple[int, int, int, int, int, int, bytes]


class CoreFramer(CoreState):
    def __init__(self, cfg: Config) -> None:
        super().__init__(cfg)
        self.buf = bytearray()
        self.times: list[int] = []
        self.marks: list[tuple[int, int]] = []
        self.head = 0
        self.base = 0
        self.last_us: int | None = NO_TIME
        self.silent = False
        self.final = False
        self.run = 0
        self.run_error = 0

    def reset(self) -> None:
        self.discarded[5] += len(self.buf) - self.head
        self.base += len(self.buf)
        self.buf.clear()
        self.times.clear()
        self.marks.clear()
        self.head = 0
        self.run = 0
        self.silent = self.final = False
        self.ctx.pending = False

    def _compact(self) -> None:
        keep = self.head
        if keep == 0:
            return
        del self.buf[:keep]
        del self.times[:keep]
        self.base += keep
        self.head = 0
        m = 0
        while m < len(self.marks) and self.marks[m][0] <= self.base:
            m += 1
        if m:
            del self.marks[:m]

    def feed(self, data: bytes, now_us: int) -> int:
        self._compact()
        if self.final and len(self.buf) > self.head:
            return 0
        cfg = self.cfg
        char = cfg.char_us
        now_us = time_clamp(now_us)
        n_in = len(data)
        i = 0
        while i < n_in and len(self.buf) < FRAMER_CAP:
            at = sat_sub(now_us, sat_mul(n_in - 1 - i, char))
            flags = 0
            if self.last_us is not None:
                if at < self.last_us:
                    at = self.last_us
                silence = sat_sub(sat_sub(at, char), self.last_us)
                if cfg.t35_us > 0 and silence >= cfg.t35_us:
                    closes = cfg.strict or silence >= cfg.flush_us
                    if len(self.buf) > self.head and (
                        not self.silent or (closes and not self.final)
                    ):
                        self.silent = True
                        self.final = closes
                        return i
                    flags = MARK_T15 | MARK_T35
                elif cfg.t15_us > 0 and silence > cfg.t15_us:
                    flags = MARK_T15
            if flags and len(self.buf) > self.head:
                self.marks.append((self.base + len(self.buf), flags))
            self.silent = self.final = False
            self.buf.append(data[i])
            self.times.append(at)
            self.last_us = at
            i += 1
        return i

    def handle_timer(self, now_us: int) -> None:
        if len(self.buf) <= self.head or self.last_us is None:
            return
        silence = sat_sub(time_clamp(now_us), self.last_us)
        if silence >= self.cfg.t35_us:
            self.silent = True
            if self.cfg.strict or silence >= self.cfg.flush_us:
                self.final = True

    def deadline(self) -> int | None:
        """None for no timer, as INT64_MAX in C (also when the deadline saturates)."""
        if len(self.buf) <= self.head or self.last_us is None:
            return None
        at = None
        if not self.silent:
            at = sat_add(self.last_us, self.cfg.t35_us)
        elif not self.final:
            at = sat_add(self.last_us, self.cfg.flush_us)
        return None if at is None or at == INT64_MAX else at

    def _event(self, at: int, length: int, kind: int, error: int) -> Event:
        return (
            self.base + at,
            length,
            kind,
            error,
            sat_sub(self.times[at], self.cfg.char_us),
            self.times[at + length - 1],
            bytes(self.buf[at : at + length]),
        )

    def _emit_run(self) -> Event:
        ev = self._event(self.head - self.run, self.run, KIND_DISCARD, self.run_error)
        self.discard_events += 1
        self.run = 0
        return ev

    def poll(self) -> Event | None:
        self._compact()
        cfg = self.cfg
        while True:
            unresolved = len(self.buf) - self.head
            if unresolved == 0:
                self.silent = self.final = False
                return self._emit_run() if self.run else None
            v = self._head_view()
            action, length, code = try_head(cfg, self.ctx, v, True)
            if action == ACT_DISCARD:
                if self.run == 0:
                    self.run_error = code
                self.run += length
                self.head += length
                self.discarded[self.run_error] += length
                continue
            if self.run:
                return self._emit_run()
            if action == ACT_WAIT:
                return None
            ev = self._event(self.head, length, code, 0)
            self.ctx.update(code, v.data)
            self.frames[code] += 1
            self.head += length
            return ev

    def sent(self, adu: bytes) -> None:
        if self.cfg.role == ROLE_MASTER and len(adu) >= 2 and adu[0] != 0:
            self.ctx.pending, self.ctx.address, self.ctx.function = True, adu[0], adu[1]
        else:
            self.ctx.pending = False

    def needed(self) -> int:
        """Bytes still needed at the head (see rtu_framer_needed in csrc/rtu.h)."""
        return head_needed(self.cfg, self.ctx, self._head_view())

    def _head_view(self) -> View:
        """The window at the head of the unresolved bytes (at most max_adu) with the
        silence marks after its start (rtu_framer_head_view)."""
        unresolved = len(self.buf) - self.head
        window = min(unresolved, self.cfg.max_adu)
        base = self.base + self.head
        mi = 0
        while mi < len(self.marks) and self.marks[mi][0] <= base:
            mi += 1
        return View(
            bytes(self.buf[self.head : self.head + window]),
            base,
            self.marks,
            mi,
            self.silent and window == unresolved,
            self.final or window < unresolved,
            True,
        )
