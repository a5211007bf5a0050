"""The virtual RS-485 bus: delivery, echo, collisions, faults, unplug, capture."""

from __future__ import annotations

import errno
import itertools
import os
import random
import select
import termios
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from pyrtu import add_crc
from pyrtu.core.timing import bits_per_char
from pyrtu.vbus import (
    Faults,
    VirtualBus,
    collision_byte,
    load_capture,
    read_capture,
)

FAST = 230400  # functional tests: fast wire, short runs


adu = add_crc  # the ADU of address + PDU, CRC low byte first (the core's own tests check it)


def open_drop(bus: VirtualBus, drop: int) -> int:
    fd = os.open(bus.paths[drop], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    assert bus.wait_clients(drop, 1)
    return fd


def read_n(fd: int, n: int, timeout: float = 3.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout
    while len(out) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        if select.select([fd], [], [], left)[0]:
            out += os.read(fd, 4096)
    return bytes(out)


def read_quiet(fd: int, quiet: float = 0.05, timeout: float = 3.0) -> bytes:
    """Read until nothing arrived for `quiet` seconds."""
    out = bytearray()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not select.select([fd], [], [], quiet)[0]:
            break
        out += os.read(fd, 4096)
    return bytes(out)


def read_timed(fd: int, n: int, timeout: float = 3.0) -> list[tuple[float, bytes]]:
    out: list[tuple[float, bytes]] = []
    got = 0
    deadline = time.monotonic() + timeout
    while got < n and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.5)[0]:
            chunk = os.read(fd, 4096)
            out.append((time.perf_counter(), chunk))
            got += len(chunk)
    return out


@pytest.fixture
def bus3() -> Iterator[VirtualBus]:
    with VirtualBus(3, baudrate=FAST) as bus:
        yield bus


def test_paths_are_ptys_and_symlinks(bus3: VirtualBus) -> None:
    assert len(bus3) == 3
    for i, path in enumerate(bus3.paths):
        assert os.path.basename(path) == f"drop{i}"
        assert os.path.islink(path)
        assert os.path.realpath(path) == bus3.tty_paths[i]
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        assert os.isatty(fd)
        os.close(fd)


def test_bytes_cross_between_drops_intact(bus3: VirtualBus) -> None:
    fds = [open_drop(bus3, i) for i in range(3)]
    payload = random.Random(1).randbytes(600)
    os.write(fds[0], payload)
    assert read_n(fds[1], len(payload)) == payload
    assert read_n(fds[2], len(payload)) == payload
    assert read_quiet(fds[0], 0.02) == b""  # no echo by default
    os.write(fds[2], b"\x00\xff back")
    assert read_n(fds[0], 7) == b"\x00\xff back"
    assert read_n(fds[1], 7) == b"\x00\xff back"
    c = bus3.counters()
    assert c.wire_bytes == 607
    assert c.collisions == 0
    assert [d.tx_bytes for d in c.drops] == [600, 0, 7]
    assert [d.rx_bytes for d in c.drops] == [7, 607, 600]
    for fd in fds:
        os.close(fd)


def test_pyserial_opens_8n1_and_8n2(bus3: VirtualBus) -> None:
    serial = pytest.importorskip("serial")
    with (
        serial.Serial(bus3.paths[0], 19200, timeout=1) as a,
        serial.Serial(bus3.paths[1], 19200, stopbits=2, timeout=1) as b,
    ):
        assert bus3.wait_clients(0) and bus3.wait_clients(1)
        a.write(b"hello")
        assert b.read(5) == b"hello"


def test_ptys_carry_no_parity(bus3: VirtualBus) -> None:
    """The documented limitation, both ways it shows up on Linux."""
    serial = pytest.importorskip("serial")
    fd = os.open(bus3.paths[2], os.O_RDWR | os.O_NOCTTY)
    try:
        attrs = termios.tcgetattr(fd)
        attrs[2] |= termios.PARENB  # asking for parity alone: EINVAL
        with pytest.raises(termios.error) as err:
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        assert err.value.args[0] == errno.EINVAL
    finally:
        os.close(fd)
    # pyserial changes other flags in the same call: accepted, parity dropped.
    with (
        serial.Serial(bus3.paths[0], 19200, parity="E", timeout=1) as a,
        serial.Serial(bus3.paths[1], 19200, timeout=1) as b,
    ):
        assert not termios.tcgetattr(a.fd)[2] & termios.PARENB
        assert bus3.wait_clients(0) and bus3.wait_clients(1)
        a.write(b"8E1 client")
        assert b.read(10) == b"8E1 client"


def test_echo_drop_hears_itself() -> None:
    with VirtualBus(2, baudrate=FAST, echo=[0]) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        os.write(a, b"ping")
        assert read_n(a, 4) == b"ping"  # echo
        assert read_n(b, 4) == b"ping"
        os.write(b, b"pong")
        assert read_n(a, 4) == b"pong"
        assert read_quiet(b, 0.02) == b""  # drop1 has no echo
        bus.set_echo(0, False)
        os.write(a, b"x")
        assert read_n(b, 1) == b"x"
        assert read_quiet(a, 0.02) == b""
        os.close(a)
        os.close(b)


def test_collision_corrupts_and_is_counted() -> None:
    with VirtualBus(3, baudrate=9600, echo=[0]) as bus:
        a, b, c = (open_drop(bus, i) for i in range(3))
        msg_a, msg_b = b"A" * 10, b"\x0f" * 10
        os.write(a, msg_a)
        os.write(b, msg_b)  # microseconds later: both transmit at once
        seen = read_n(c, 20)
        echo = read_n(a, 20)  # drop0 echoes what is on the wire: corrupted
        heard_by_b = read_n(b, 10)
        counters = bus.counters()
        assert counters.collisions == 1
        assert counters.collided_bytes == 20
        assert counters.drops[0].collisions == counters.drops[1].collisions == 1
        assert counters.drops[0].collided_bytes == counters.drops[1].collided_bytes == 10
        garbled = collision_byte(ord("A"), 0x0F)  # what receivers see: 'A' ^ 0x0f
        assert seen == echo == bytes([garbled]) * 20
        assert heard_by_b == bytes([garbled]) * 10
        # Sequential traffic does not collide.
        assert bus.wait_idle()
        os.write(b, b"ok")
        assert read_n(c, 2) == b"ok"
        assert bus.counters().collisions == 1
        for fd in (a, b, c):
            os.close(fd)


def test_collision_byte_always_differs() -> None:
    for x in range(256):
        for y in range(256):
            assert collision_byte(x, y) != x


def test_unheard_drop_gets_no_stale_bytes(bus3: VirtualBus) -> None:
    a, b = open_drop(bus3, 0), open_drop(bus3, 1)
    os.write(a, b"nobody on drop2 hears this")
    assert read_n(b, 26) == b"nobody on drop2 hears this"
    if bus3.clients(2) < 0:
        pytest.skip("inotify not available: drops without client buffer bytes")
    late = open_drop(bus3, 2)
    assert read_quiet(late, 0.05) == b""
    assert bus3.counters().drops[2].unheard == 26
    os.write(a, b"now")
    assert read_n(late, 3) == b"now"
    for fd in (a, b, late):
        os.close(fd)


# -- faults --------------------------------------------------------------------


def run_faulted(faults: Faults, payload: bytes, baud: int = FAST) -> tuple[bytes, dict[str, int]]:
    """Send `payload` from drop0 (faulted) to drop1; what drop1 got, fault counts."""
    with VirtualBus(2, baudrate=baud, drop_faults={0: faults}) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        for i in range(0, len(payload), 100):  # several writes: chunking must not matter
            os.write(a, payload[i : i + 100])
        got = read_quiet(b, 0.1, timeout=10)
        counters = bus.counters().faults
        os.close(a)
        os.close(b)
    return got, counters


PAYLOAD = random.Random(42).randbytes(1500)


def test_bit_flips_seeded() -> None:
    f = Faults(seed=7, bit_flip_rate=0.01)
    got, counters = run_faulted(f, PAYLOAD)
    assert len(got) == len(PAYLOAD)
    flipped = sum(bin(x ^ y).count("1") for x, y in zip(got, PAYLOAD, strict=True))
    assert flipped == counters["bit_flips"]
    assert 60 < flipped < 190  # 12000 bits at 1 %
    assert run_faulted(f, PAYLOAD)[0] == got  # same seed, same flips
    assert run_faulted(Faults(seed=8, bit_flip_rate=0.01), PAYLOAD)[0] != got


def is_subsequence(short: bytes, long: bytes) -> bool:
    it = iter(long)
    return all(b in it for b in short)


def test_dropped_bytes_seeded() -> None:
    f = Faults(seed=3, drop_rate=0.05)
    got, counters = run_faulted(f, PAYLOAD)
    assert 30 < counters["dropped"] < 130
    assert len(got) == len(PAYLOAD) - counters["dropped"]
    assert is_subsequence(got, PAYLOAD)
    assert run_faulted(f, PAYLOAD)[0] == got
    assert run_faulted(Faults(seed=4, drop_rate=0.05), PAYLOAD)[0] != got


def test_inserted_bytes_seeded() -> None:
    f = Faults(seed=5, insert_rate=0.05)
    got, counters = run_faulted(f, PAYLOAD)
    assert 30 < counters["inserted"] < 130
    assert len(got) == len(PAYLOAD) + counters["inserted"]
    assert is_subsequence(PAYLOAD, got)
    assert run_faulted(f, PAYLOAD)[0] == got
    assert run_faulted(Faults(seed=6, insert_rate=0.05), PAYLOAD)[0] != got


def gap_run(faults: Faults, tmp_path: Path, name: str) -> list[int]:
    """Lengths of the silence-separated runs on the wire, from a capture."""
    cap = str(tmp_path / name)
    with VirtualBus(2, baudrate=115200, drop_faults={0: faults}, capture=cap) as bus:
        a = open_drop(bus, 0)
        os.write(a, PAYLOAD[:120])
        time.sleep(0.01)
        assert bus.wait_idle()
        os.close(a)
    return [len(r.data) for r in sorted(load_capture(cap).records, key=lambda r: r.t_us)]


def test_inserted_gaps(tmp_path: Path) -> None:
    # Every 16th byte waits 4 character times (> t3.5): runs of 15 then 16 bytes.
    char = bits_per_char("E", 1, 8) / 115200
    every = gap_run(Faults(gap_every=16, gap_s=4 * char), tmp_path, "every.cap")
    assert every == [15] + [16] * 6 + [9]
    # Random gaps of 2 characters (between t1.5 and t3.5), seeded.
    f = Faults(seed=11, gap_rate=0.05, gap_s=2 * char)
    runs = gap_run(f, tmp_path, "rand1.cap")
    assert sum(runs) == 120 and len(runs) > 2
    assert gap_run(f, tmp_path, "rand2.cap") == runs
    assert gap_run(Faults(seed=12, gap_rate=0.05, gap_s=2 * char), tmp_path, "rand3.cap") != runs
    data, chunks = read_capture(str(tmp_path / "rand1.cap"))
    # one chunk per run of back-to-back bytes, timed at its last byte
    assert [b[0] - a[0] for a, b in itertools.pairwise(chunks)] == runs[:-1]
    ends = [t for _, t in chunks]
    firsts = [t - (n - 1) * char for t, n in zip(ends, runs, strict=True)]
    silences = [b - a - char for a, b in zip(ends, firsts[1:], strict=False)]
    assert all(s > char for s in silences)
    assert data == PAYLOAD[:120]


def burst_sizes(faults: Faults) -> list[int]:
    with VirtualBus(2, baudrate=9600, drop_faults={1: faults}) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        os.write(a, PAYLOAD[:60])
        chunks = read_timed(b, 60)
        os.close(a)
        os.close(b)
    assert sum(len(c) for _, c in chunks) == 60
    return [len(c) for _, c in chunks]


def test_split_delivery_in_bursts() -> None:
    char = bits_per_char("E", 1, 8) / 9600
    # FTDI-style: held bytes are released 14.5 character times after the first one.
    f = Faults(seed=1, batch_s=14.5 * char)
    sizes = burst_sizes(f)
    assert sizes == [15, 15, 15, 15]
    assert burst_sizes(f) == sizes  # reproducible
    # ... or as soon as batch_bytes are held.
    assert burst_sizes(Faults(batch_s=14.5 * char, batch_bytes=10)) == [10] * 6


def test_unplug_mid_frame() -> None:
    with VirtualBus(2, baudrate=FAST) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        bus.unplug(0, after_bytes=3)
        os.write(a, adu(b"\x01\x03\x00\x00\x00\x02"))
        assert read_quiet(b, 0.05) == b"\x01\x03\x00"  # the device vanished mid-frame
        counters = bus.counters()
        assert counters.drops[0].unplugged and counters.faults["unplugs"] == 1
        assert not os.path.lexists(os.path.join(bus.directory, "drop0"))
        with pytest.raises(OSError) as err:  # the port is gone: EIO, as for a USB adapter
            os.write(a, b"more")
        assert err.value.errno == errno.EIO
        assert os.read(a, 10) == b""  # hang-up
        os.close(a)
        # Plug it back in: a new pty behind the same path.
        path = bus.replug(0)
        a = open_drop(bus, 0)
        assert path == bus.paths[0]
        os.write(a, b"back")
        assert read_n(b, 4) == b"back"
        os.close(a)
        os.close(b)


def test_unplug_fault_reproducible() -> None:
    f = Faults(seed=2, unplug_after=5)
    got1, c1 = run_faulted(f, PAYLOAD[:40])
    got2, c2 = run_faulted(f, PAYLOAD[:40])
    assert got1 == got2 == PAYLOAD[:5]
    assert c1["unplugs"] == c2["unplugs"] == 1


def test_faults_validation() -> None:
    with pytest.raises(ValueError):
        Faults(bit_flip_rate=1.5)
    with pytest.raises(ValueError):
        Faults(gap_every=4)  # no gap_s
    with pytest.raises(ValueError):
        VirtualBus(0)
    with pytest.raises(ValueError):
        VirtualBus(2, parity="X")
    assert not Faults(batch_s=0.016).line_faults
    assert bits_per_char("E", 1, 8) == bits_per_char("N", 2, 8) == 11
    assert bits_per_char("N", 1, 8) == 10


# -- capture -------------------------------------------------------------------


def test_capture_round_trips_through_parse_stream(tmp_path: Path) -> None:
    pyrtu = pytest.importorskip("pyrtu")
    cap = str(tmp_path / "bus.cap")
    request = adu(b"\x11\x03\x00\x6b\x00\x03")
    response = adu(b"\x11\x03\x06\x02\x2b\x00\x00\x00\x64")
    with VirtualBus(3, baudrate=9600, parity="E", capture=cap) as bus:
        master, slave = open_drop(bus, 0), open_drop(bus, 1)
        for _ in range(3):
            os.write(master, request)
            assert read_n(slave, len(request)) == request
            time.sleep(0.005)  # the slave's turnaround
            os.write(slave, response)
            assert read_n(master, len(response)) == response
            time.sleep(0.005)
        assert bus.wait_idle()
        os.close(master)
        os.close(slave)

    data, chunks = read_capture(cap)
    assert data == (request + response) * 3
    assert [o for o, _ in chunks] == [0, 8, 19, 27, 38, 46]  # a chunk per frame on the wire
    assert all(b[1] > a[1] for a, b in itertools.pairwise(chunks))
    frames = pyrtu.parse_stream(data, "monitor", chunks=chunks, baudrate=9600, parity="E")
    kinds = [f.kind for f in frames]
    assert kinds == [pyrtu.FrameKind.REQUEST, pyrtu.FrameKind.RESPONSE] * 3
    assert all(f.error is None for f in frames)
    assert [f.adu for f in frames] == [request, response] * 3
    assert frames[1].address == 0x11 and frames[1].function == 3
    # Strict mode (t1.5/t3.5 checked on the captured times) agrees: no gaps inside.
    strict = pyrtu.parse_stream(data, "monitor", chunks=chunks, baudrate=9600, strict=True)
    assert [f.adu for f in strict] == [request, response] * 3

    loaded = load_capture(cap)
    assert loaded.header.baudrate == 9600 and loaded.header.bits == 11
    assert [r.drop for r in sorted(loaded.records, key=lambda r: r.t_us)] == [0, 1] * 3
    assert not any(r.collision for r in loaded.records)
    assert list(loaded.drops[: len(request)]) == [0] * len(request)
    assert list(loaded.drops[len(request) : len(request) + len(response)]) == [1] * len(response)
    assert [f.adu for f in loaded.parse()] == [request, response] * 3
    # Each frame takes its wire time in the capture: 8 characters of 11 bits.
    char = 11 / 9600
    span = loaded.times[len(request) - 1] - loaded.times[0]
    assert span == pytest.approx((len(request) - 1) * char, abs=2e-6)


def test_capture_flags_collisions(tmp_path: Path) -> None:
    cap = str(tmp_path / "coll.cap")
    with VirtualBus(3, baudrate=9600, capture=cap) as bus:
        a, b = open_drop(bus, 0), open_drop(bus, 1)
        os.write(a, b"\x01" * 6)
        os.write(b, b"\x02" * 6)  # microseconds later: every character collides
        time.sleep(0.01)
        assert bus.wait_idle()
        os.close(a)
        os.close(b)
    loaded = load_capture(cap)
    assert {r.drop for r in loaded.records} == {0, 1}
    assert all(r.collision for r in loaded.records)
    assert loaded.data.count(b"\x03") == 12  # 0x01 ^ 0x02
