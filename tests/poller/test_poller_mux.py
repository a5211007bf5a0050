"""The poller's ``tcp://`` buses on its mux (`pyrtu.poller.muxdrive`): which buses
run there, the answers' times (the kernel's receive time, though the mux is
collected on a grid of ticks), a write answered as it comes (not a tick later),
retries, and a fault of the poller in a step supervised like a bus task's.  Real
sockets: a scripted Modbus TCP server (its answers built here with `struct`,
Messaging on TCP/IP Implementation Guide V1.0b 3.1.3) on a thread."""

from __future__ import annotations

import asyncio
import itertools
import logging
import socket
import statistics
import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from waiting import wait_for

from pyrtu.pdu.errors import NoResponseError
from pyrtu.poller import Bus, Point, Poller, TaskFailed, make_config, muxdrive
from pyrtu.poller.events import Event
from pyrtu.poller.muxdrive import collect_tick, on_mux

PATIENCE = 30.0


class Scripted:
    """A Modbus TCP server on a thread: holding registers ``regs``; ``delay``
    seconds before each answer; ``drop``: requests it ignores (counted down);
    FC 6 writes a register.  ``requests``: the PDUs it was sent."""

    def __init__(self, regs: list[int], delay: float = 0.0) -> None:
        self.regs = regs
        self.delay = delay
        self.drop = 0
        self.requests: list[bytes] = []
        self.tids: list[int] = []  # their transaction ids
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = int(self.sock.getsockname()[1])
        self._stop = False
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._client, args=(conn,), daemon=True).start()

    def _client(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            while True:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                buf += data
                while len(buf) >= 7 and len(buf) >= 6 + struct.unpack(">H", buf[4:6])[0]:
                    n = 6 + struct.unpack(">H", buf[4:6])[0]
                    adu, buf = buf[:n], buf[n:]
                    tid, _, _, unit = struct.unpack(">HHHB", adu[:7])
                    pdu = adu[7:]
                    self.requests.append(pdu)
                    self.tids.append(tid)
                    if self.drop:
                        self.drop -= 1
                        continue
                    if pdu[0] == 3:
                        address, count = struct.unpack(">HH", pdu[1:5])
                        words = self.regs[address : address + count]
                        answer = bytes((3, 2 * count)) + struct.pack(f">{count}H", *words)
                    elif pdu[0] == 6:
                        address, value = struct.unpack(">HH", pdu[1:5])
                        self.regs[address] = value
                        answer = pdu
                    else:
                        answer = bytes((pdu[0] | 0x80, 1))
                    if self.delay:
                        time.sleep(self.delay)
                    conn.sendall(struct.pack(">HHHB", tid, 0, len(answer) + 1, unit) + answer)

    def close(self) -> None:
        self._stop = True
        self.sock.close()


@pytest.fixture
def server() -> Iterator[Scripted]:
    srv = Scripted([100 + i for i in range(10)])
    yield srv
    srv.close()


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def test_plain_tcp_buses_run_on_the_mux_the_others_on_their_own_master() -> None:
    assert on_mux(Bus("a", "tcp://127.0.0.1:1502", {}))
    assert on_mux(Bus("b", "tcp://127.0.0.1:1502", {"timeout": 0.5, "retries": 2}))
    assert not on_mux(Bus("c", "udp://127.0.0.1:1502", {}))
    assert not on_mux(Bus("d", "rtu+tcp://127.0.0.1:1502", {}))
    assert not on_mux(Bus("e", "/dev/ttyUSB0", {}))
    buses = [Bus("a", "tcp://127.0.0.1:1502", {}), Bus("c", "udp://127.0.0.1:1502", {})]
    points = [Point(f"{b.name}.x", b.name, 1, "holding", 0) for b in buses]
    auto = Poller(make_config(buses, points))
    assert {n: r.on_mux for n, r in auto._runs.items()} == {"a": True, "c": False}
    aio = Poller(make_config(buses, points), master="aio")
    assert not any(r.on_mux for r in aio._runs.values())


def test_without_a_mux_here_every_bus_has_a_master_of_its_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where there is no mux (a platform whose only selector is select()), ``auto``
    gives the tcp:// buses an `AsyncMaster` each."""
    monkeypatch.setattr(muxdrive, "available", lambda: False)
    bus = Bus("a", "tcp://127.0.0.1:1502", {})
    poller = Poller(make_config([bus], [Point("a.x", "a", 1, "holding", 0)]))
    assert not poller._runs["a"].on_mux


def test_the_collection_grid_is_the_finest_wake_grid() -> None:
    assert collect_tick([0.01, 0.002, 0.0]) == 0.002
    assert collect_tick([0.0]) == 0.01  # (no bus with points: 10 ms)


def poller_of(server: Scripted, interval: float, **master: Any) -> Poller:
    bus = Bus("t", f"tcp://127.0.0.1:{server.port}", {"timeout": 1.0, **master})
    point = Point("t.r0", "t", 1, "holding", 0, interval=interval)
    return Poller(make_config([bus], [point]))


@pytest.mark.wall_clock
def test_an_answers_time_is_when_it_came_not_when_it_was_collected(server: Scripted) -> None:
    """Collected every 25 ms (2.5 % of a 1 s interval), an answer that takes 30 ms
    has a latency of 30 ms and a bit, not that of a collection's tick."""
    server.delay = 0.030
    latencies: list[float] = []

    async def main() -> None:
        poller = poller_of(server, 1.0)
        poller.on_latency(lambda bus, slave, seconds: latencies.append(seconds))
        async with poller:
            await until(lambda: len(latencies) >= 7, "seven answers")

    asyncio.run(main())
    tick = 0.025
    # (the first two left out: Linux turns receive time-stamping on for the whole
    # system a moment after the first socket asks, tests/tcp/test_tcp_mux.py)
    latencies = latencies[2:]
    # each at least the server's delay; past it by the loopback's time, far less
    # than the tick: taken when collected, the answer that came at 30 ms would
    # be seen at a tick after it, 50 or 75 ms after the request
    assert all(0.030 <= s for s in latencies), latencies
    assert statistics.median(latencies) < 0.030 + tick / 4, latencies


@pytest.mark.wall_clock
def test_a_write_is_collected_as_it_comes_not_at_the_next_tick(server: Scripted) -> None:
    """Writes someone awaits are read as they come: their median round trip is far
    below the 25 ms collection tick (half of it on average without that)."""
    took: list[float] = []

    async def main() -> None:
        poller = poller_of(server, 1.0)
        async with poller:
            await until(lambda: poller.last("t.r0") is not None, "a first read")
            for i in range(15):
                t0 = time.monotonic()
                await poller.write_registers("t", 1, "holding", 1, [i])
                took.append(time.monotonic() - t0)
                await asyncio.sleep(0.003 * (i % 4))  # (anywhere between two ticks)
            assert server.regs[1] == 14  # the writes went through, in order
            assert await poller.read_registers("t", 1, "holding", 1, 1) == [14]

    asyncio.run(main())
    assert statistics.median(took) < 0.01 / 4, took


def test_a_retry_answers_what_the_first_attempt_did_not(server: Scripted) -> None:
    async def main() -> None:
        poller = poller_of(server, 5.0, retries=1, timeout=0.2)
        async with poller:
            await until(lambda: poller.last("t.r0") is not None, "a first read")
            server.drop = 1  # the next request goes unanswered: the retry is answered
            n = len(server.requests)
            assert await poller.read_registers("t", 1, "holding", 2, 2) == [102, 103]
            assert server.requests[n:] == [bytes((3, 0, 2, 0, 2))] * 2

    asyncio.run(main())


def test_without_retries_an_unanswered_read_fails(server: Scripted) -> None:
    async def main() -> None:
        poller = poller_of(server, 5.0)
        async with poller:
            await until(lambda: poller.last("t.r0") is not None, "a first read")
            server.drop = 1
            with pytest.raises(NoResponseError):
                await poller.read_registers("t", 1, "holding", 2, 2)
            assert await poller.read_registers("t", 1, "holding", 2, 2) == [102, 103]

    asyncio.run(main())


def test_a_fault_in_a_step_is_supervised_and_the_bus_polls_on(server: Scripted) -> None:
    """The scheduler's ``on_response`` made to raise twice (the fault is the
    point): one `TaskFailed`, the bus's ``task_failures`` counted, values again."""
    events: list[Event] = []
    answers: list[float] = []

    async def main() -> None:
        poller = poller_of(server, 0.05)
        poller.on_event(events.append)
        poller.on_latency(lambda bus, slave, seconds: answers.append(seconds))
        sched = poller.scheduler("t")
        real, calls = sched.on_response, [0]

        def failing(*args: Any, **kwargs: Any) -> Any:
            calls[0] += 1
            if 3 < calls[0] <= 5:
                raise RuntimeError("injected")
            return real(*args, **kwargs)

        sched.on_response = failing  # type: ignore[method-assign]
        async with poller:
            await until(lambda: calls[0] > 8, "polls after the faults")
            (bus,) = poller.bus_summary()
            assert bus["task_failures"] == 2

    asyncio.run(main())
    failed = [e for e in events if isinstance(e, TaskFailed)]
    assert len(failed) == 1 and "injected" in failed[0].error  # reported once


def test_every_frame_is_logged_at_debug_level(
    server: Scripted, caplog: pytest.LogCaptureFixture
) -> None:
    """``pyrtu -vv``: the mux's transactions log their frames as the asyncio
    client's do (the request's ADU and the answer's, built here with `struct`)."""
    caplog.set_level(logging.DEBUG, logger="pyrtu.drivers.master")

    async def main() -> None:
        poller = poller_of(server, 5.0)
        async with poller:
            await until(lambda: poller.last("t.r0") is not None, "a first read")

    asyncio.run(main())
    tx = [r.getMessage() for r in caplog.records if r.getMessage().startswith("TX unit 1")]
    rx = [r.getMessage() for r in caplog.records if r.getMessage().startswith("RX unit 1")]
    assert tx and rx
    request = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 1).hex(" ")
    answer = struct.pack(">HHHBBBH", 1, 0, 5, 1, 3, 2, 100).hex(" ")
    assert tx[0].endswith(request) and rx[0].startswith(f"RX unit 1 fc 3 tid 1: {answer} (")


# ------------------------------------------------------------ the steady state


@pytest.fixture
def sends(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The requests the driver submits itself (the mux's repeats not among them)."""
    sent: list[int] = []
    real = muxdrive.MuxDriver._send

    def counted(self: muxdrive.MuxDriver, d: Any) -> bool:
        sent.append(len(sent))
        return real(self, d)

    monkeypatch.setattr(muxdrive.MuxDriver, "_send", counted)
    return sent


def consecutive(tids: list[int]) -> bool:
    return all((b - a) & 0xFFFF == 1 for a, b in itertools.pairwise(tids))


def test_a_steady_poll_is_sent_by_the_mux_and_every_answer_still_counts(
    server: Scripted, sends: list[int]
) -> None:
    """A lone block answering the same: after its first request the mux repeats it
    (no submit of the driver's), each answer still reaches ``on_latency`` and the
    statistics, the transaction ids follow one another, and a changed value is
    delivered as it comes."""
    latencies: list[float] = []
    updates: list[Any] = []

    async def main() -> None:
        poller = poller_of(server, 0.02)
        poller.on_latency(lambda bus, slave, seconds: latencies.append(seconds))
        poller.on_update(updates.append)
        async with poller:
            await until(lambda: len(server.requests) >= 10, "ten polls")
            assert len(sends) == 1  # the first only: the mux sent the rest
            server.regs[0] = 7
            await until(lambda: any(u.value == 7 for u in updates), "the changed value")
            await until(lambda: len(server.requests) >= 30, "twenty more polls")
            assert len(sends) == 1  # a change does not end the repeat
        (st,) = poller.summary()["slaves"]
        assert st["requests"] == st["responses"] == len(latencies)
        assert len(server.requests) - 1 <= st["requests"] <= len(server.requests)

    asyncio.run(main())
    assert consecutive(server.tids)
    assert [u.value for u in updates] == [100, 7]


@pytest.mark.wall_clock
def test_a_repeated_polls_latency_is_its_own_not_the_first_requests(server: Scripted) -> None:
    """Each answer's latency runs from its own request (a loopback answer: well
    under an interval), not from the first: that of the 30th would be 29
    intervals."""
    latencies: list[float] = []

    async def main() -> None:
        poller = poller_of(server, 0.02)
        poller.on_latency(lambda bus, slave, seconds: latencies.append(seconds))
        async with poller:
            await until(lambda: len(latencies) >= 30, "thirty answers")

    asyncio.run(main())
    assert max(latencies) < 25 * 0.02, latencies


@pytest.mark.parametrize("delay", [0.0, 0.1])
def test_a_write_during_a_steady_poll_goes_out_and_the_poll_goes_on(
    server: Scripted, sends: list[int], delay: float
) -> None:
    """Whether the repeat is idle or has a transaction in flight (answered after
    ``delay``, longer than the interval: in flight nearly all the time)."""
    server.delay = delay

    async def main() -> None:
        poller = poller_of(server, 0.02)
        async with poller:
            await until(lambda: len(server.requests) >= 5, "five polls")
            await poller.write_registers("t", 1, "holding", 1, [42])
            assert server.regs[1] == 42
            n = len(server.requests)
            await until(lambda: len(server.requests) >= n + 5, "five polls after it")
            # the write, then one poll of the driver's, the rest the mux's again
            assert len(sends) == 3

    asyncio.run(main())
    assert bytes((6, 0, 1, 0, 42)) in server.requests
    assert consecutive(server.tids)  # the write's id follows the repeats'


def test_an_unanswered_repeat_ends_it_and_is_retried_then_the_repeat_resumes(
    server: Scripted, sends: list[int]
) -> None:
    events: list[Event] = []

    async def main() -> None:
        poller = poller_of(server, 0.05, retries=1, timeout=0.2)
        poller.on_event(events.append)
        async with poller:
            await until(lambda: len(server.requests) >= 4, "four polls")
            assert len(sends) == 1
            server.drop = 1  # a repeat goes unanswered: the driver retries it
            n = len(server.requests)
            await until(lambda: len(server.requests) >= n + 6, "polls after it")
            assert len(sends) == 3  # the retry, then the poll that repeats again
            (st,) = poller.summary()["slaves"]
            assert st["timeouts"] == 0 and st["responses"] >= n  # (the retry answered)

    asyncio.run(main())
    assert consecutive(server.tids)
    assert not [e for e in events if isinstance(e, TaskFailed)]


def test_debug_switched_on_during_a_steady_poll_logs_its_frames(
    server: Scripted, caplog: pytest.LogCaptureFixture, sends: list[int]
) -> None:
    async def main() -> None:
        poller = poller_of(server, 0.02)
        async with poller:
            await until(lambda: len(server.requests) >= 5, "five polls")
            assert len(sends) == 1
            caplog.set_level(logging.DEBUG, logger="pyrtu.drivers.master")
            await until(lambda: len(sends) >= 4, "polls the driver sends itself")

    asyncio.run(main())
    tx = [r.getMessage() for r in caplog.records if r.getMessage().startswith("TX unit 1")]
    assert len(tx) >= 3
