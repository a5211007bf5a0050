"""Which loop runs the hub (the C I/O thread or the Python loop), and moving between them."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from c_core import needs_c
from test_vbus import open_drop, read_n

import pyrtu
from pyrtu.vbus import Faults, VirtualBus

FAST = 230400
C_LOOP = pyrtu.BACKEND == "c"
needs_c_loop = needs_c(not C_LOOP, "the C loop needs the C core as the backend")


def test_the_loop_follows_the_backend_and_the_configuration(tmp_path: Path) -> None:
    with VirtualBus(2, baudrate=FAST) as bus:
        assert bus.loop == ("c" if C_LOOP else "python")
    with VirtualBus(2, baudrate=FAST, loop="python") as bus:
        assert bus.loop == "python"
    with VirtualBus(2, baudrate=FAST, capture=str(tmp_path / "a.cap")) as bus:
        assert bus.loop == "python"  # the capture is the Python loop's
    with VirtualBus(2, baudrate=FAST, drop_faults={1: Faults(seed=1, drop_rate=0.1)}) as bus:
        assert bus.loop == "python"  # seeded line faults are Python's random.Random
    with VirtualBus(2, baudrate=FAST, faults=Faults(batch_s=0.001, unplug_after=99)) as bus:
        assert bus.loop == ("c" if C_LOOP else "python")  # batch and unplug: both loops


def test_a_bad_loop_name_is_refused() -> None:
    with pytest.raises(ValueError, match="loop"):
        VirtualBus(2, loop="fast")


@needs_c_loop
def test_line_faults_move_a_running_bus_to_the_python_loop() -> None:
    with VirtualBus(3, baudrate=FAST, echo=[0]) as bus:
        assert bus.loop == "c"
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        try:
            os.write(a, b"before")
            assert read_n(b, 6) == b"before"
            bus.set_faults(Faults(seed=3, drop_rate=1.0), drop=2)  # drop 2 loses everything
            assert bus.loop == "python" and bus.running
            os.write(a, b"after")
            assert read_n(b, 5) == b"after"
            assert read_n(a, 11) == b"beforeafter"  # the echo setting moved over too
            c = bus.counters()
            assert c.wire_bytes == 11 and c.drops[0].tx_bytes == 11 and c.drops[1].rx_bytes == 11
        finally:
            os.close(a)
            os.close(b)


@needs_c_loop
def test_unplug_and_replug_on_the_c_loop() -> None:
    with VirtualBus(2, baudrate=FAST) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        try:
            bus.unplug(1, after_bytes=3)
            os.write(b, b"abcdef")
            assert read_n(a, 6, timeout=0.5) == b"abc"
            deadline = time.monotonic() + 2
            while not os.path.lexists(bus.paths[1]) and time.monotonic() < deadline:
                time.sleep(0.001)
            while os.path.lexists(bus.paths[1]) and time.monotonic() < deadline:
                time.sleep(0.001)
            assert not os.path.lexists(bus.paths[1])
            assert bus.counters().drops[1].unplugged and bus.counters().faults["unplugs"] == 1
            bus.replug(1)
            b2 = open_drop(bus, 1)
            os.write(a, b"back")
            assert read_n(b2, 4) == b"back"
            os.close(b2)
        finally:
            os.close(a)
            os.close(b)


GIL_HOG = r"""
import os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY)
print("ready", flush=True)
got = b""
while len(got) < int(sys.argv[2]):
    got += os.read(fd, 4096)
print(time.perf_counter_ns(), flush=True)
"""


@needs_c_loop
@pytest.mark.wall_clock
def test_the_c_loop_delivers_while_python_holds_the_gil() -> None:
    """The C loop needs no GIL: a frame crosses the bus while this process's main
    thread computes in Python with a switch interval of 2 s (no other thread of
    this process runs Python meanwhile).  Bound: the frame's wire time plus 100 ms
    of slack for a loaded 2-core VM (process wake-ups, the reader's start), against
    the 500 ms the hog holds the GIL: the Python loop would deliver nothing before
    the hog ends."""
    frame = bytes(range(64))
    with VirtualBus(2, baudrate=FAST) as bus:
        reader = subprocess.Popen(
            [sys.executable, "-c", GIL_HOG, bus.paths[1], str(len(frame))],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert reader.stdout is not None
        try:
            assert reader.stdout.readline().strip() == "ready"
            a = open_drop(bus, 0)
            assert bus.wait_clients(1, 1)
            old = sys.getswitchinterval()
            sys.setswitchinterval(2.0)
            try:
                t0 = time.perf_counter_ns()
                os.write(a, frame)
                x = 0
                while time.perf_counter_ns() - t0 < 500_000_000:  # pure Python: holds the GIL
                    x += 1
            finally:
                sys.setswitchinterval(old)
            arrived = int(reader.stdout.readline())
            os.close(a)
        finally:
            reader.kill()
            reader.wait()
        wire_ns = len(frame) * bus.char_ns
        assert arrived - t0 < wire_ns + 100_000_000, (arrived - t0) / 1e6
