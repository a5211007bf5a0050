"""The C schedule (csrc/rtu_vbus.c) and I/O thread (csrc/rtu_vbus_io.c) for the hub.

`CSchedule` has the interface of the twin `pyrtu.core._pure.vbus.Schedule` (without its
Python-only capture and line faults); `CLoop` runs the C I/O thread's loop.  Both
exist only when the C core is built (`available`).
"""

from __future__ import annotations

from typing import Any

from pyrtu.core import _backend
from pyrtu.core._pure.vbus import COUNTERS, _time

__all__ = ["CLoop", "CSchedule", "available"]

_C = _backend.C
#: the C loop can run here: the C core is built with its POSIX I/O and is the active backend
available = _C is not None and _backend.active is _C and bool(_C.POSIX_IO)
_NO_TIME = -(2**63)


def _lib() -> tuple[Any, Any]:
    if _C is None:
        raise ImportError("the pyrtu C core is not built")
    return _C.ffi, _C.lib


class CSchedule:
    """rtu_vbus behind the twin's interface (the caller holds the lock, if any)."""

    def __init__(self, ndrops: int, char_ns: int, lead_ns: int) -> None:
        ffi, lib = _lib()
        for name, v in (("ndrops", ndrops), ("char_ns", char_ns), ("lead_ns", lead_ns)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"{name} must be an integer, not {type(v).__name__}")
        if not 1 <= ndrops <= lib.RTU_VBUS_MAX_DROPS:
            raise ValueError(f"ndrops must be 1..{lib.RTU_VBUS_MAX_DROPS}, not {ndrops}")
        if not 1 <= char_ns <= lib.RTU_VBUS_MAX_CHAR_NS or not 0 <= lead_ns <= (
            lib.RTU_VBUS_MAX_LEAD_NS
        ):
            raise ValueError(
                f"char_ns must be 1..{lib.RTU_VBUS_MAX_CHAR_NS} and lead_ns"
                f" 0..{lib.RTU_VBUS_MAX_LEAD_NS}"
            )
        self._ffi, self._lib = ffi, lib
        self.ndrops = ndrops
        self.drops = ffi.new("rtu_vbus_drop[]", ndrops)
        self.s = ffi.new("rtu_vbus *")
        if lib.rtu_vbus_init(self.s, self.drops, ndrops, char_ns, lead_ns) != lib.RTU_OK:
            raise ValueError("rtu_vbus_init refused the configuration")
        self.char_ns = char_ns
        self.lead_ns = lead_ns

    def _i(self, i: int) -> int:
        if isinstance(i, bool) or not isinstance(i, int):
            raise TypeError(f"drop must be an integer, not {type(i).__name__}")
        if not 0 <= i < self.ndrops:
            raise IndexError(f"no drop {i} on a {self.ndrops}-drop bus")
        return i

    @property
    def wire_bytes(self) -> int:
        return int(self.s.wire_bytes)

    @property
    def collisions(self) -> int:
        return int(self.s.collisions)

    @property
    def collided(self) -> int:
        return int(self.s.collided)

    def plug(self, i: int) -> None:
        self._lib.rtu_vbus_plug(self.s, self._i(i))

    def unplug(self, i: int) -> None:
        self._lib.rtu_vbus_unplug(self.s, self._i(i))

    def set_echo(self, i: int, on: bool) -> None:
        self._lib.rtu_vbus_set_echo(self.s, self._i(i), bool(on))

    def set_batch(self, i: int, batch_ns: int, batch_bytes: int) -> None:
        self._i(i)
        if not 0 <= batch_ns <= 3600 * 10**9 or not 1 <= batch_bytes <= self._lib.RTU_VBUS_OUT:
            raise ValueError(f"batch must be 0..1 h and 1..{self._lib.RTU_VBUS_OUT} bytes")
        self._lib.rtu_vbus_set_batch(self.s, i, batch_ns, batch_bytes)

    def set_unplug_after(self, i: int, left: int | None) -> None:
        self._lib.rtu_vbus_set_unplug_after(self.s, self._i(i), -1 if left is None else left)

    def cut(self, i: int, at: int) -> None:
        self._lib.rtu_vbus_cut(self.s, self._i(i), _time(at, "at"))

    def clear_hold(self, i: int) -> None:
        self._lib.rtu_vbus_clear_hold(self.s, self._i(i))

    def space(self, i: int) -> int:
        return int(self._lib.rtu_vbus_space(self.s, self._i(i)))

    def transmit(self, i: int, data: bytes, now: int) -> None:
        self._i(i)
        _time(now, "now")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be bytes-like, not {type(data).__name__}")
        buf = self._ffi.from_buffer("uint8_t[]", data)
        status = self._lib.rtu_vbus_transmit(self.s, i, buf, len(buf), now)
        if status == self._lib.RTU_ENOSPC:
            free = self.space(i)
            raise BufferError(f"drop {i}: {len(data)} bytes for {free} free slots")
        if status != self._lib.RTU_OK:
            raise ValueError("the wire would run past the clock's range")

    def deadline(self) -> int | None:
        t = int(self._lib.rtu_vbus_deadline(self.s))
        return None if t == _NO_TIME else t

    def service(self, now: int) -> list[int]:
        self._lib.rtu_vbus_service(self.s, _time(now, "now"))
        return self.take_due()

    def take_due(self) -> list[int]:
        due = []
        while (i := int(self._lib.rtu_vbus_take_due(self.s))) >= 0:
            due.append(i)
        return due

    def take_output(self, i: int) -> bytes:
        d = self.drops[self._i(i)]
        return bytes(self._ffi.buffer(d.out, d.out_len))

    def written(self, i: int, n: int, heard: int) -> None:
        d = self.drops[self._i(i)]
        if not 0 <= n <= d.out_len:
            raise ValueError(f"written: n must be 0..{d.out_len}, not {n}")
        self._lib.rtu_vbus_written(self.s, i, n, heard)

    def busy(self) -> bool:
        return bool(self._lib.rtu_vbus_busy(self.s))

    def drop_counters(self, i: int) -> dict[str, int]:
        c = self.drops[self._i(i)].counters
        return {name: int(getattr(c, name)) for name in COUNTERS}

    def alive(self, i: int) -> bool:
        return bool(self.drops[self._i(i)].alive)

    def held(self, i: int) -> bytes:
        """What the drop's batch fault holds back."""
        d = self.drops[self._i(i)]
        return bytes(self._ffi.buffer(d.hold, d.hold_len))

    def queued(self, i: int) -> list[tuple[int, int]]:
        """The drop's queued character slots (start, byte), for a move to the twin."""
        d = self.drops[self._i(i)]
        mask = len(d.q_time) - 1
        return [
            (int(d.q_time[(d.q_head + k) & mask]), int(d.q_byte[(d.q_head + k) & mask]))
            for k in range(d.q_len)
        ]


class CLoop:
    """The C I/O thread's state (rtu_vbus_io) over a `CSchedule`."""

    STOPPED = WATCH = UNPLUG = 0

    def __init__(self, sched: CSchedule, wake_fd: int, watch_fd: int, anchor_ns: int) -> None:
        ffi, lib = _lib()
        self._ffi, self._lib = ffi, lib
        self.sched = sched
        self._mem = ffi.new("char[]", int(lib.rtu_vbus_io_size()) + 64)
        addr = int(ffi.cast("uintptr_t", self._mem))
        self.io = ffi.cast("rtu_vbus_io *", self._mem + (-addr % 64))
        if lib.rtu_vbus_io_init(self.io, sched.s, wake_fd, watch_fd, anchor_ns) != lib.RTU_OK:
            raise OSError("rtu_vbus_io_init failed (no POSIX I/O here?)")
        self.STOPPED = lib.RTU_VBUS_IO_STOPPED
        self.WATCH = lib.RTU_VBUS_IO_WATCH
        self.UNPLUG = lib.RTU_VBUS_IO_UNPLUG
        self.ERRNO = lib.RTU_VBUS_IO_ERRNO

    def lock(self) -> None:
        self._lib.rtu_vbus_io_lock(self.io)

    def unlock(self) -> None:
        self._lib.rtu_vbus_io_unlock(self.io)

    def set_fd(self, i: int, fd: int, heard: bool) -> None:
        self._lib.rtu_vbus_io_set_fd(self.io, i, fd, heard)

    def set_heard(self, i: int, heard: bool) -> None:
        self._lib.rtu_vbus_io_set_heard(self.io, i, heard)

    def stop(self) -> None:
        self._lib.rtu_vbus_io_stop(self.io)

    def run(self) -> int:
        """Run the loop (the GIL is released) until Python has work; the reason."""
        return int(self._lib.rtu_vbus_io_run(self.io))

    def errno(self) -> int:
        return int(self._lib.rtu_vbus_io_errno(self.io))

    def wakeups(self) -> int:
        return int(self._lib.rtu_vbus_io_wakeups(self.io))

    def destroy(self) -> None:
        self._lib.rtu_vbus_io_destroy(self.io)
