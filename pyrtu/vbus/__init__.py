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
  ``pyrtu.parse_stream(data, "monitor", chunks=chunks, ...)``.

Parity
------

Linux pseudo-terminals reject parity (``tcsetattr`` with PARENB fails with
EINVAL), so clients must open the drops as 8N1 or 8N2.  The parity of the bus is
a timing parameter only: a bus configured 8E1 (the default, as in the Modbus
specification) uses 11-bit characters; no parity bit is carried or checked.

Clock: all times are `time.perf_counter` (CLOCK_MONOTONIC on Linux).
"""

from __future__ import annotations

from .capture import (
    Capture,
    CaptureHeader,
    CaptureRecord,
    load_capture,
    read_capture,
)
from .faults import FaultCounters, Faults, collision_byte
from .hub import BusCounters, DropCounters, VirtualBus, bits_per_char

__all__ = [
    "BusCounters",
    "Capture",
    "CaptureHeader",
    "CaptureRecord",
    "DropCounters",
    "FaultCounters",
    "Faults",
    "VirtualBus",
    "bits_per_char",
    "collision_byte",
    "load_capture",
    "read_capture",
]
