"""The xfer step (pyrtu.drivers.xfer: csrc/rtu_xfer_io.c and its twin
pyrtu/drivers/_pyxfer.py) on a real pseudo-terminal, on both backends: what it sends,
reads and reports, and that C and the twin agree, errors included."""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Iterator
from types import ModuleType

import pytest

from pyrtu.drivers import xfer, xfer_runners
from pyrtu.protocol.client_actions import Xfer


def plan(
    fd: int,
    drain: bool,
    request: bytes,
    send_at: float,
    char: float,
    first_wake: float = 0.0,
    timeout: float = 0.0,
    expect: int = 0,
    short_len: int = 0,
    look: bool = True,
    spin: float = 0.0,
) -> xfer.XferPlan:
    """An xfer's plan from its values one by one."""
    ex = Xfer(request, send_at, first_wake, timeout, expect, short_len)
    return xfer.XferPlan(fd, drain, char, ex, look, spin)


REQUEST = bytes.fromhex("0703000000 0a c4 6f".replace(" ", ""))
CHAR = 10 / 115200


@pytest.fixture
def pty() -> Iterator[tuple[int, int]]:
    """(device, line): ``line`` is the tty end the xfer runner uses (raw, non-blocking),
    ``device`` the other end, which plays the slave."""
    device, line = os.openpty()
    tty.setraw(line)
    os.set_blocking(line, False)
    yield device, line
    for fd in (device, line):
        try:
            os.close(fd)
        except OSError:
            pass


def answer_of(count: int, backend: ModuleType) -> bytes:
    return backend.add_crc(bytes((7, 3, 2 * count)) + bytes(range(2 * count)))  # type: ignore[no-any-return]


def play(device: int, replies: list[tuple[float, bytes]], got: list[bytes]) -> threading.Thread:
    """A slave thread: read the request, then write each reply chunk ``delay``
    seconds after the previous one."""

    def run() -> None:
        got.append(os.read(device, 256))
        for delay, chunk in replies:
            time.sleep(delay)
            os.write(device, chunk)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def run(
    backend: ModuleType,
    line: int,
    *,
    expect: int,
    timeout: float = 0.5,
    send_at: float = 0.0,
    first_wake: float = 0.002,
) -> xfer.XferResult:
    ex = xfer_runners.xfer_runner(backend)
    return ex.run(plan(line, False, REQUEST, send_at, CHAR, first_wake, timeout, expect, 5))  # type: ignore[no-any-return]


def test_an_answer_in_pieces_is_read_whole(backend: ModuleType, pty: tuple[int, int]) -> None:
    device, line = pty
    answer = answer_of(10, backend)
    got: list[bytes] = []
    t = play(device, [(0.003, answer[:5]), (0.003, answer[5:])], got)
    r = run(backend, line, expect=len(answer))
    t.join(2)
    assert got == [REQUEST]
    assert r.status == xfer.ANSWER and r.sent and r.data == answer
    assert 1 <= r.first_n <= len(answer) and 1 <= r.reads <= 4
    assert r.start <= r.end <= r.first_t <= r.last_t
    assert r.err == r.stage == 0


def test_a_real_line_is_drained_and_timed(backend: ModuleType, pty: tuple[int, int]) -> None:
    """``drain``: tcdrain after the write, and the transmission never ends before its
    characters' time on the line."""
    device, line = pty
    answer = answer_of(2, backend)
    got: list[bytes] = []
    t = play(device, [(0.002, answer)], got)
    slow = 10 / 1200  # 1200 baud: 8 characters take 66.7 ms
    slow_plan = plan(line, True, REQUEST, 0.0, slow, 0.0, 0.5, len(answer), 5)
    r = xfer_runners.xfer_runner(backend).run(slow_plan)
    t.join(2)
    assert r.status == xfer.ANSWER and r.data == answer and got == [REQUEST]
    assert r.end >= r.start + len(REQUEST) * slow - 1e-6


def test_stale_input_at_the_send_time_sends_nothing(
    backend: ModuleType, pty: tuple[int, int]
) -> None:
    device, line = pty
    os.write(device, b"\x01\x02\x03")
    time.sleep(0.01)
    r = run(backend, line, expect=25, send_at=time.monotonic() + 0.002)
    assert r.status == xfer.STALE and not r.sent and r.data == b"\x01\x02\x03"
    assert r.last_t >= r.start  # (start: 0, nothing was written)
    os.set_blocking(device, False)
    with pytest.raises(BlockingIOError):
        os.read(device, 64)  # the request never went


def test_the_send_time_is_kept(backend: ModuleType, pty: tuple[int, int]) -> None:
    device, line = pty
    answer = answer_of(2, backend)
    got: list[bytes] = []
    t = play(device, [(0.0, answer)], got)
    at = time.monotonic() + 0.02
    r = run(backend, line, expect=len(answer), send_at=at)
    t.join(2)
    assert r.status == xfer.ANSWER and r.start >= at


@pytest.mark.wall_clock  # bounded by half the xfer's deadline
def test_an_exception_answer_ends_the_xfer(backend: ModuleType, pty: tuple[int, int]) -> None:
    device, line = pty
    exc = backend.add_crc(bytes((7, 0x83, 2)))
    got: list[bytes] = []
    t = play(device, [(0.002, exc)], got)
    r = run(backend, line, expect=25, timeout=5.0)
    t.join(2)
    assert r.status == xfer.ANSWER and r.data == exc
    assert r.last_t - r.end < 2.5  # not the 5 s deadline


@pytest.mark.wall_clock  # bounded by half the xfer's deadline
def test_no_answer_ends_at_the_deadline(backend: ModuleType, pty: tuple[int, int]) -> None:
    device, line = pty
    got: list[bytes] = []
    t = play(device, [], got)
    r = run(backend, line, expect=25, timeout=0.05)
    t.join(2)
    assert r.status == xfer.SHORT and r.sent and r.data == b"" and r.first_n == 0
    assert time.monotonic() - r.end >= 0.05


def test_a_short_answer_is_reported_with_its_bytes(
    backend: ModuleType, pty: tuple[int, int]
) -> None:
    device, line = pty
    got: list[bytes] = []
    t = play(device, [(0.001, b"\x07\x03\x14\x00")], got)
    r = run(backend, line, expect=25, timeout=0.1)
    t.join(2)
    assert r.status == xfer.SHORT and r.data == b"\x07\x03\x14\x00" and r.reads == 1


def test_a_vanished_device_is_an_error(backend: ModuleType, pty: tuple[int, int]) -> None:
    device, line = pty
    got: list[bytes] = []
    t = play(device, [], got)
    t.join(2)
    os.close(device)  # the other end goes: the tty reports EIO (a pulled adapter)
    r = run(backend, line, expect=25, timeout=0.2)
    assert r.status in (xfer.ERRNO, xfer.GONE)
    if r.status == xfer.ERRNO:
        assert r.err and r.stage in (xfer.STAGE_READ, xfer.STAGE_WRITE)


def test_the_backends_agree(both: tuple[ModuleType, ModuleType]) -> None:
    """The same scenarios on C and on the twin report the same (times aside)."""
    outcomes = []
    for backend in both:
        seen = []
        for replies, expect, timeout in (
            ([(0.002, answer_of(10, backend))], 25, 0.5),
            ([(0.002, answer_of(10, backend)[:7])], 25, 0.05),
            ([(0.002, backend.add_crc(b"\x07\x83\x02"))], 25, 0.5),
            ([], 25, 0.02),
        ):
            device, line = os.openpty()
            try:
                tty.setraw(line)
                os.set_blocking(line, False)
                got: list[bytes] = []
                t = play(device, replies, got)
                r = run(backend, line, expect=expect, timeout=timeout)
                t.join(2)
                seen.append((r.status, r.sent, r.data, got))
            finally:
                os.close(device)
                os.close(line)
        outcomes.append(seen)
    assert outcomes[0] == outcomes[1]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"request": b""}, "request must not be empty"),
        ({"expect": -1}, "expect must be 0..4096, not -1"),
        ({"expect": 5000}, "expect must be 0..4096, not 5000"),
        ({"short_len": 30}, r"short_len must be 0..expect \(25\), not 30"),
        ({"char": 0.0}, "char must be a positive number of seconds, not 0.0"),
        ({"timeout": -1.0}, "first_wake and timeout must be non-negative"),
        ({"fd": -1}, "fd must be an open descriptor, not -1"),
        ({"spin": -1e-6}, r"spin must be 0..0.001 seconds, not -1e-06"),
        ({"spin": 0.002}, r"spin must be 0..0.001 seconds, not 0.002"),
        ({"spin": float("nan")}, r"spin must be 0..0.001 seconds, not nan"),
    ],
)
def test_bad_arguments_are_refused_alike(
    backend: ModuleType, change: dict[str, object], message: str
) -> None:
    args: dict[str, object] = {
        "fd": 0,
        "drain": False,
        "request": REQUEST,
        "send_at": 0.0,
        "first_wake": 0.0,
        "timeout": 0.1,
        "char": CHAR,
        "expect": 25,
        "short_len": 5,
    }
    args.update(change)
    with pytest.raises(ValueError, match=message):
        xfer_runners.xfer_runner(backend).run(plan(**args))  # type: ignore[arg-type]


def test_the_async_xfer_runner_runs_on_its_thread(
    backend: ModuleType, pty: tuple[int, int]
) -> None:
    """`AsyncXferRunner`: submit returns at once, the pipe wakes the caller when the
    xfer is over, the report is `XferRunner`'s; one xfer at a time."""
    import select

    device, line = pty
    answer = answer_of(10, backend)
    ax = xfer_runners.async_xfer_runner(backend)
    try:
        for _ in range(2):
            got: list[bytes] = []
            t = play(device, [(0.003, answer)], got)
            ax.submit(plan(line, False, REQUEST, 0.0, CHAR, 0.002, 0.5, len(answer), 5))
            with pytest.raises(RuntimeError, match="under way"):
                ax.submit(plan(line, False, REQUEST, 0.0, CHAR, 0.002, 0.5, len(answer), 5))
            assert select.select([ax.fd], [], [], 2.0)[0] == [ax.fd]
            r = ax.result()
            t.join(2)
            assert r is not None and r.status == xfer.ANSWER and r.data == answer
            assert got == [REQUEST]
            assert ax.result() == r  # the last xfer's report, until the next
    finally:
        ax.close()
    with pytest.raises(ValueError, match="closed"):
        ax.submit(plan(line, False, REQUEST, 0.0, CHAR, 0.002, 0.5, 25, 5))


def test_a_response_goes_at_its_time(backend: ModuleType, pty: tuple[int, int]) -> None:
    """Nothing awaited (``expect`` 0, a slave's response): written at ``send_at``,
    without a look for input (``look`` false: input pending then is not the
    writer's business)."""
    device, line = pty
    os.write(device, b"\x09")  # input waiting on the line: sent all the same
    answer = answer_of(2, backend)
    at = time.monotonic() + 0.01
    r = xfer_runners.xfer_runner(backend).run(plan(line, False, answer, at, CHAR, look=False))
    assert r.status == xfer.ANSWER and r.sent and r.start >= at and r.data == b""
    assert os.read(device, 64) == answer


@pytest.mark.wall_clock  # a quarter character at 115200 (the median of 15 writes)
def test_a_response_with_spin_is_written_at_its_time(
    backend: ModuleType, pty: tuple[int, int]
) -> None:
    """``spin``: the last of the wait before the write is on the clock, not a sleep
    (which overshoots by a wake-up's latency): never before its time, and at the
    median of a round of 15 writes within a quarter character at 115200 baud of it.
    A loaded machine can hold the thread off the CPU for a whole round (a wake-up
    late by a third of a millisecond: no spin makes up for it): up to 20 rounds,
    one of which must be on time.  Without the spin no round is (a sleep's wake-up
    is late by tens of µs every time: about 80 µs on this VM)."""
    device, line = pty
    answer = answer_of(2, backend)
    ex = xfer_runners.xfer_runner(backend)
    medians = []
    for _round in range(20):
        late = []
        for _ in range(15):
            at = time.monotonic() + 0.003
            r = ex.run(plan(line, False, answer, at, CHAR, look=False, spin=xfer.SPIN_MAX))
            assert r.status == xfer.ANSWER and r.start >= at
            assert os.read(device, 64) == answer
            late.append(r.start - at)
        medians.append(sorted(late)[len(late) // 2])
        if medians[-1] < CHAR / 4:
            break
    assert medians[-1] < CHAR / 4, [f"{m * 1e6:.1f} us" for m in medians]


@pytest.mark.wall_clock  # bounded by half the xfer's deadline
def test_cancel_ends_an_xfer(backend: ModuleType, pty: tuple[int, int]) -> None:
    """`AsyncXferRunner.cancel`: before the send time nothing is written; while an
    answer is awaited the wait ends at once; either way the report comes."""
    import select

    device, line = pty
    os.set_blocking(device, False)
    ax = xfer_runners.async_xfer_runner(backend)
    try:
        ax.submit(plan(line, False, REQUEST, time.monotonic() + 5.0, CHAR, 0.0, 0.5, 25, 5))
        time.sleep(0.02)
        ax.cancel()
        assert select.select([ax.fd], [], [], 2.0)[0] == [ax.fd]
        r = ax.result()
        assert r is not None and r.status == xfer.CANCELLED and not r.sent
        with pytest.raises(BlockingIOError):
            os.read(device, 64)  # nothing went
        start = time.monotonic()
        ax.submit(plan(line, False, REQUEST, 0.0, CHAR, 0.0, 5.0, 25, 5))  # no answer comes
        time.sleep(0.02)
        ax.cancel()
        assert select.select([ax.fd], [], [], 2.0)[0] == [ax.fd]
        r = ax.result()
        assert r is not None and r.status == xfer.CANCELLED and r.sent
        assert time.monotonic() - start < 2.5  # not the 5 s deadline
        assert os.read(device, 64) == REQUEST
    finally:
        ax.close()
