"""AsyncMaster against the sync pyrtu Slave: pseudo-terminals and the virtual bus, RTU and
ASCII, many ports in one event loop, the per-bus queue, cancellation mid-transaction, a
port that vanishes mid-transaction, and a pyserial URL port read in a worker thread."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from ptylink import PtyLink, ScriptedSlave, make_store, serving
from waiting import ANSWER_TIMEOUT

from pyrtu import add_crc
from pyrtu import pdu as pdus
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncMaster, new_event_loop, run
from pyrtu.pdu.errors import ExceptionResponseError, FrameError, ModbusError, PortError

vbus = pytest.importorskip("pyrtu.vbus")
MODES = ("rtu", "ascii")


def regs_answer(slave: int, values: list[int]) -> bytes:
    body = bytes((slave, 3, 2 * len(values))) + b"".join(v.to_bytes(2, "big") for v in values)
    return add_crc(body)


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture(params=MODES)
def mode(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def test_every_method_on_a_pty(backend: ModuleType, mode: str) -> None:
    be = backend.BACKEND
    with (
        PtyLink() as link,
        serving(link.path_b, store=make_store(), t35=0, backend=be, mode=mode) as slave,
    ):

        async def main() -> None:
            async with AsyncMaster(
                link.path_a, parity="N", t35=0, timeout=0.5, backend=be, mode=mode
            ) as m:
                assert m.line.mode == mode and m.last_answer_time is None
                assert await m.read_coils(1, 0, 10) == [i % 3 == 0 for i in range(10)]
                assert await m.read_holding_registers(1, 0, 125) == [1000 + i for i in range(125)]
                assert await m.read_input_registers(1, 90, 3) == [2090, 2091, 2092]
                await m.write_register(1, 3, 77)
                await m.write_registers(1, 4, [5, 6])
                await m.write_coil(1, 1, True)
                await m.write_coils(1, 2, [True, False])
                await m.mask_write_register(1, 3, 0x00F0, 0x0001)
                assert await m.read_write_registers(1, 3, 3, 10, [9]) == [(77 & 0xF0) | 1, 5, 6]
                assert await m.read_discrete_inputs(1, 3, 2) == [False, True]
                assert await m.request(1, pdus.read_request(3, 0, 2)) == bytes.fromhex(
                    "030403e803e9"
                )
                with pytest.raises(ExceptionResponseError) as info:
                    await m.read_holding_registers(1, 250, 1)
                assert info.value.code == 2
                assert isinstance(await m.get_comm_event_counter(1), tuple)
                assert m.last_answer_time is not None
                assert m.last_answer_time <= time.monotonic()
                c = m.counters
                assert c["exceptions"] == 1 and c["timeouts"] == 0 and c["frame_errors"] == 0

        run(main())
        assert slave.counters["requests"] >= 13


def _uvloop_run(main: Any) -> Any:
    uvloop = pytest.importorskip("uvloop")
    return uvloop.run(main)


#: every event loop the masters keep their timing on (pyrtu.drivers._ptimer: a timerfd on
#: the loops whose own timers are whole milliseconds)
RUNNERS: dict[str, Callable[[Any], Any]] = {
    "pyrtu": run,
    "asyncio": asyncio.run,
    "uvloop": _uvloop_run,
}


@pytest.mark.parametrize("runner", sorted(RUNNERS))
@pytest.mark.parametrize("mode", MODES)
def test_virtual_bus_three_slaves(mode: str, runner: str) -> None:
    baud = 38400
    with vbus.VirtualBus(4, baudrate=baud, parity="E") as bus, contextlib.ExitStack() as stack:
        for a in (1, 2, 3):
            stack.enter_context(
                serving(bus.paths[a], address=a, store=make_store(), baudrate=baud, mode=mode)
            )

        async def main() -> None:
            line = LineConfig(baudrate=baud, parity="N", mode=mode)
            async with AsyncMaster(bus.paths[0], line=line, timeout=ANSWER_TIMEOUT) as m:
                for i in range(30):
                    a = 1 + i % 3
                    assert await m.read_holding_registers(a, i, 4) == [
                        1000 + i + k for k in range(4)
                    ]
                await m.write_register(0, 150, 9)  # broadcast
                await asyncio.sleep(0.05)
                for a in (1, 2, 3):
                    assert await m.read_holding_registers(a, 150, 1) == [9]
                assert m.counters["responses"] == 33 and m.counters["broadcasts"] == 1

        RUNNERS[runner](main())
        assert bus.counters().collisions == 0


def test_many_ports_in_one_loop() -> None:
    ports = 4
    with contextlib.ExitStack() as stack:
        links = [stack.enter_context(PtyLink()) for _ in range(ports)]
        for link in links:
            stack.enter_context(serving(link.path_b, store=make_store(), t35=0))
        spans: dict[int, list[tuple[float, float]]] = {i: [] for i in range(ports)}

        async def poll(i: int, m: AsyncMaster) -> None:
            for k in range(40):
                start = time.monotonic()
                assert await m.read_holding_registers(1, k, 5) == [1000 + k + j for j in range(5)]
                spans[i].append((start, time.monotonic()))

        async def main() -> None:
            masters = [AsyncMaster(link.path_a, parity="N", t35=0, timeout=0.5) for link in links]
            try:
                await asyncio.gather(*(poll(i, m) for i, m in enumerate(masters)))
            finally:
                for m in masters:
                    await m.close()
            assert all(m.counters["responses"] == 40 for m in masters)

        run(main())
    # the ports ran in parallel: transactions of different ports overlapped in time
    # (one port at a time would leave every pair of spans disjoint)
    events = sorted((t, i) for i, ss in spans.items() for span in ss for t in span)
    open_ports: set[int] = set()
    overlaps = 0
    for _t, i in events:
        if i in open_ports:
            open_ports.discard(i)
        else:
            overlaps += bool(open_ports)
            open_ports.add(i)
    assert overlaps > 0


def test_per_bus_queue_is_first_come_first_served() -> None:
    with PtyLink() as link, serving(link.path_b, store=make_store(), t35=0):
        done: list[int] = []

        async def one(m: AsyncMaster, k: int) -> None:
            assert await m.read_holding_registers(1, k, 1) == [1000 + k]
            done.append(k)

        async def main() -> None:
            async with AsyncMaster(link.path_a, parity="N", t35=0, timeout=0.5) as m:
                await asyncio.gather(*(one(m, k) for k in range(20)))
                assert m.counters["requests"] == 20

        run(main())
        assert done == list(range(20))


def test_cancel_mid_transaction_waits_out_the_late_answer(backend: ModuleType) -> None:
    def answer(request: bytes, n: int) -> list[tuple[float, bytes]]:
        count = request[5]
        return [
            (0.15 if n == 0 else 0.0, regs_answer(1, [100 * (n + 1) + i for i in range(count)]))
        ]

    with PtyLink() as link:
        peer = ScriptedSlave(link.path_b, answer)
        try:

            async def main() -> None:
                async with AsyncMaster(
                    link.path_a, parity="N", t35=0, timeout=1.0, backend=backend.BACKEND
                ) as m:
                    with pytest.raises(asyncio.TimeoutError):
                        await asyncio.wait_for(m.read_holding_registers(1, 0, 2), 0.05)
                    # the late answer (2 registers) arrives while this one is on its way
                    assert await m.read_holding_registers(1, 0, 3) == [200, 201, 202]
                    c = m.counters
                    assert c["responses"] == 1
                    assert c["discarded_stale"] + c["discarded_unexpected"] == 9

            run(main())
            assert len(peer.requests) == 2
        finally:
            peer.close()


@pytest.mark.wall_clock
@pytest.mark.parametrize("runner", sorted(RUNNERS))
def test_port_vanishes_mid_transaction(runner: str) -> None:
    """The master's drop is pulled out while the request is on the wire: a typed error
    within the timeout, the bus is free again, and no descriptor leaks, on every loop
    (uvloop's libuv aborts the process on a descriptor closed under its epoll)."""
    timeout = 0.3
    RUNNERS[runner](asyncio.sleep(0))  # libuv's process-wide signal pipe, made once
    before = open_fds()
    with (
        vbus.VirtualBus(2, baudrate=9600, parity="N") as bus,
        serving(bus.paths[1], store=make_store(), baudrate=9600),
    ):

        async def main() -> None:
            m = AsyncMaster(bus.paths[0], 9600, parity="N", timeout=timeout)
            try:
                assert await m.read_holding_registers(1, 0, 1) == [1000]
                bus.unplug(0, after_bytes=3)
                start = time.monotonic()
                with pytest.raises(ModbusError) as info:
                    await m.read_holding_registers(1, 0, 1)
                # bounded by the timeout (plus scheduling slack on a loaded 2-core VM:
                # one more timeout)
                assert time.monotonic() - start < 2 * timeout
                assert isinstance(info.value, PortError | FrameError) or "no response" in str(
                    info.value
                )
                # the bus is free: the next call fails at once or in a timeout, never hangs
                with pytest.raises(ModbusError):
                    await asyncio.wait_for(m.read_holding_registers(1, 0, 1), 4 * timeout)
            finally:
                await m.close()

        RUNNERS[runner](main())
    # the bus, the slave, the loop and the master are gone: every descriptor with them
    assert open_fds() == before


def test_url_port_reads_in_a_worker_thread() -> None:
    """loop:// has no descriptor: pyserial reads in the port's thread.  The loop echoes
    the request, which is not an answer (function 3 with byte count 0)."""

    async def main() -> None:
        async with AsyncMaster("loop://", parity="N", t35=0, timeout=0.3) as m:
            assert m.port.fd is None
            with pytest.raises(FrameError):
                await m.read_holding_registers(1, 0, 1)
            # a raw request on loop:// comes back as its own answer
            assert await m.request(1, bytes.fromhex("0600010002")) == bytes.fromhex("0600010002")

    run(main())


def test_default_event_loop_works_too() -> None:
    with PtyLink() as link, serving(link.path_b, store=make_store(), t35=0):

        async def main() -> list[int]:
            async with AsyncMaster(link.path_a, parity="N", t35=0, timeout=0.5) as m:
                return await m.read_holding_registers(1, 0, 2)

        assert asyncio.run(main()) == [1000, 1001]
        loop = new_event_loop()
        loop.close()


def test_arguments_checked_before_the_port_opens() -> None:
    for kwargs, name in (
        ({"timeout": float("inf")}, "timeout"),
        ({"timeout": float("nan")}, "timeout"),
        ({"timeout": 0}, "timeout"),
        ({"retries": -1}, "retries"),
        ({"broadcast_delay": float("inf")}, "broadcast_delay"),
        ({"mode": "tcp"}, "mode"),
        ({"baudrate": 0}, "baudrate"),
    ):
        with pytest.raises(ValueError, match=name):
            AsyncMaster("/dev/pyrtu-no-such-port", **kwargs)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="not both"):
        AsyncMaster("/dev/pyrtu-no-such-port", 9600, line=LineConfig())


def test_max_in_flight_is_for_tcp_only(tmp_path: Path) -> None:
    """AsyncMaster takes ``max_in_flight`` (tcp:// keeps several requests on the
    wire); a serial line refuses anything but 1 before its port is opened."""
    missing = str(tmp_path / "no-such-port")
    with pytest.raises(ValueError, match="max_in_flight must be 1 on a serial line"):
        AsyncMaster(missing, 9600, max_in_flight=4)
    with pytest.raises(TypeError, match="max_in_flight must be an integer"):
        AsyncMaster(missing, 9600, max_in_flight=True)
    tcp = AsyncMaster("tcp://127.0.0.1:1", max_in_flight=4)  # connects on first use
    assert type(tcp) is AsyncMaster and tcp.mode == "tcp"  # one class, a TCP link


@pytest.mark.wall_clock
@pytest.mark.parametrize("runner", sorted(RUNNERS))
def test_a_cancelled_xfer_frees_the_port_at_once(runner: str, backend: ModuleType) -> None:
    """A repeated read (an `Xfer` on the port's xfer thread) cancelled while it
    waits for an answer that will not come: the thread's xfer ends at once, the
    next read waits for nothing but the protocol's settling, and close is prompt
    (bounds: a fraction of the 2 s response timeout)."""
    timeout = 2.0
    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:

        async def main() -> None:
            m = AsyncMaster(bus.paths[0], 115200, parity="N", timeout=timeout,
                            backend=backend.BACKEND)  # fmt: skip
            try:
                with serving(bus.paths[1], store=make_store(), baudrate=115200):
                    for _ in range(3):  # the answer's length learned: xfers from now
                        assert await m.read_holding_registers(1, 0, 2) == [1000, 1001]
                assert m._ax is not None  # the xfer thread ran them
                start = time.monotonic()
                with pytest.raises(asyncio.TimeoutError):  # nobody answers now
                    await asyncio.wait_for(m.read_holding_registers(1, 0, 2), 0.05)
                with serving(bus.paths[1], store=make_store(), baudrate=115200):
                    assert await m.read_holding_registers(1, 0, 2) == [1000, 1001]
                assert time.monotonic() - start < timeout / 2
            finally:
                start = time.monotonic()
                await m.close()
                assert time.monotonic() - start < timeout / 2

        RUNNERS[runner](main())


@pytest.mark.wall_clock  # the read after it: within 0.5 s (the old xfer's deadline 1 s)
def test_an_xfer_left_by_an_ended_loop_is_waited_out_in_the_next(backend: ModuleType) -> None:
    """A loop that ended while a cancelled transaction's xfer was still under way
    on the thread (its report had not reached that loop): the same AsyncMaster used
    from a new loop cancels the xfer and waits for its end on the thread, then
    reads, instead of awaiting the ended loop's future."""
    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:
        m = AsyncMaster(bus.paths[0], 115200, parity="N", timeout=1.0, backend=backend.BACKEND)
        old = asyncio.new_event_loop()

        async def learn() -> None:
            for _ in range(3):
                assert await m.read_holding_registers(1, 0, 2) == [1000, 1001]

        with serving(bus.paths[1], store=make_store(), baudrate=115200):
            old.run_until_complete(learn())
        # the slave's port is closed: nobody hears the next request, which waits for
        # its 1 s deadline on the thread
        ax = m._ax
        assert ax is not None
        ax.cancel = lambda: None  # type: ignore[method-assign]  # (the old loop's cancel is lost)
        task = old.create_task(m.read_holding_registers(1, 0, 2))
        old.run_until_complete(asyncio.sleep(0.05))
        task.cancel()
        old.run_until_complete(asyncio.gather(task, return_exceptions=True))
        assert m._ax_over is not None  # still under way on the thread
        old.close()
        del ax.cancel

        async def again() -> list[int]:
            try:
                return await asyncio.wait_for(m.read_holding_registers(1, 0, 2), 0.5)
            finally:
                await m.close()

        with serving(bus.paths[1], store=make_store(), baudrate=115200):
            assert asyncio.run(again()) == [1000, 1001]
