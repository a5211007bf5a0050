"""A virtual RS-485 bus made of pseudo-terminals.

`VirtualBus` is a hub with N drops.  Each drop is a pseudo-terminal whose path
(``DIR/drop0``, a symlink to ``/dev/pts/N``) any program can open: pyrtu,
pymodbus, minimalmodbus, libmodbus, ``cat``.  Every byte a drop transmits reaches
every other drop, one character time after the previous one, as on a half-duplex
wire::

    from pyrtu.vbus import VirtualBus, Faults

    with VirtualBus(3, baudrate=9600, parity="E", capture="bus.cap") as bus:
        master_port, slave_port, sniffer_port = bus.paths
        ...

What it models
--------------

* Wire timing: characters of ``1 + bytesize + parity + stopbits`` bits (10 or 11
  for RTU) at the bus's baud rate; a byte is delivered when its last bit is sent,
  gaps the sender leaves are kept.  A 256-byte frame at 9600 baud 8E1 takes 293 ms.
* Half duplex: characters of two drops overlapping in time collide; receivers get
  ``byte ^ other`` (``~byte`` if ``other`` is 0) and `counters` counts it.
* Echo per drop (``echo=[0]``): the sender also receives its own bytes.
* Seeded faults (`Faults`): bit flips, lost bytes, inserted bytes, inserted gaps,
  split delivery in bursts (FTDI latency timer), and `VirtualBus.unplug` for a
  drop that vanishes mid-frame.
* Capture: every byte on the wire with its time, in the format described in
  `pyrtu.vbus.capture`; `read_capture` returns ``(data, chunks)`` for
  ``pyrtu.parse_stream(data, "monitor", chunks=chunks, ...)``; `capture_frames`
  streams a capture of any size through the `Framer` in bounded memory.
* One bus per directory: ``DIR/.pyrtu-vbus.lock`` holds the running bus's pid;
  a second bus there raises `BusDirectoryBusy` (a lock left by a dead bus is taken
  over).  At most `MAX_DROPS` (248) drops: each is a pseudo-terminal.

Parity
------

Linux pseudo-terminals reject parity (``tcsetattr`` with PARENB fails with
EINVAL), so clients must open the drops as 8N1 or 8N2.  The parity of the bus is
a timing parameter only: a bus configured 8E1 (the default, as in the Modbus
specification) uses 11-bit characters; no parity bit is carried or checked.

Timing
------

The wire is a sans-I/O schedule (csrc/rtu_vbus.c, twin pyrtu/core/_pure/vbus.py) on
`time.perf_counter_ns` (CLOCK_MONOTONIC on Linux; also the clock of capture times).
One hub thread drives it: by default in C (csrc/rtu_vbus_io.c: ``ppoll`` until the
next delivery, no GIL), or in a Python ``select`` loop for the pure backend, a
capture or seeded line faults (``bus.loop`` tells).  It compensates the
pseudo-terminals' own transfer latency (``latency=``) and asks for real-time
scheduling when permitted (``realtime=``).  On the Python loop it shares the GIL with
the rest of the process: for timing work, run it as a process (``pyrtu vbus``).
Measured accuracy and the details: ``docs/vbus.md``.
"""

from __future__ import annotations

from typing import Any

from .capture import (
    Capture,
    CaptureError,
    CaptureHeader,
    CaptureReader,
    CaptureRecord,
    capture_frames,
    load_capture,
    read_capture,
    stream_frames,
)
from .faults import FaultCounters, Faults, collision_byte

try:  # the hub is made of pseudo-terminals: POSIX only (termios, fcntl, tty)
    from ._lock import BusDirectoryBusy
    from .hub import MAX_DROPS, BusCounters, DropCounters, VirtualBus
except ImportError as _exc:
    if _exc.name not in ("termios", "fcntl", "tty"):
        raise
    _NO_PTY = _exc  # captures and faults still work here (Windows)

    def __getattr__(name: str) -> Any:
        if name in ("MAX_DROPS", "BusDirectoryBusy", "BusCounters", "DropCounters", "VirtualBus"):
            raise ImportError(
                f"pyrtu.vbus.{name} needs POSIX pseudo-terminals; this Python has no "
                f"{_NO_PTY.name} module (Windows?): run the virtual bus on Linux or macOS"
            ) from _NO_PTY
        raise AttributeError(f"module 'pyrtu.vbus' has no attribute {name!r}")


__all__ = [
    "MAX_DROPS",
    "BusCounters",
    "BusDirectoryBusy",
    "Capture",
    "CaptureError",
    "CaptureHeader",
    "CaptureReader",
    "CaptureRecord",
    "DropCounters",
    "FaultCounters",
    "Faults",
    "VirtualBus",
    "capture_frames",
    "collision_byte",
    "load_capture",
    "read_capture",
    "stream_frames",
]
