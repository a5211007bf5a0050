"""Master and slaves on the virtual RS-485 bus (wire timing, collisions detected by the
hub): a shared bus of three pyrtu slaves, ASCII, echoing drops, broadcast, and noise
with USB-style batching where every failure is a typed error and no wrong value is
ever returned."""

from __future__ import annotations

import contextlib
import random
import time
from collections.abc import Iterator

import pytest
from ptylink import make_store, serving

from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import FrameError, ModbusError, NoResponseError

vbus = pytest.importorskip("pyrtu.vbus")
VirtualBus = vbus.VirtualBus
Faults = vbus.Faults

BAUD = 38400


@contextlib.contextmanager
def shared_bus(
    mode: str = "rtu", echo: tuple[int, ...] = (), faults: object = None, **master_options: object
) -> Iterator[tuple[Master, list[Slave], object]]:
    """Drop 0: the master; drops 1-3: pyrtu slaves 1-3, all with the spec's timing."""
    with VirtualBus(4, baudrate=BAUD, parity="E", echo=echo, faults=faults) as bus:
        paths = bus.paths
        with contextlib.ExitStack() as stack:
            slaves = [
                stack.enter_context(
                    serving(
                        paths[a],
                        address=a,
                        store=make_store(),
                        baudrate=BAUD,
                        mode=mode,
                        echo=a in echo,
                    )
                )
                for a in (1, 2, 3)
            ]
            options = {"timeout": 0.3, "mode": mode, "echo": 0 in echo, **master_options}
            master = stack.enter_context(Master(paths[0], BAUD, parity="N", **options))  # type: ignore[arg-type]
            yield master, slaves, bus


def test_three_slaves_share_the_bus() -> None:
    rng = random.Random(4)
    with shared_bus() as (m, slaves, bus):
        expected = {a: [1000 + i for i in range(200)] for a in (1, 2, 3)}
        for _ in range(150):
            a = rng.choice((1, 2, 3))
            start = rng.randrange(0, 190)
            if rng.random() < 0.3:
                value = rng.randrange(0x10000)
                m.write_register(a, start, value)
                expected[a][start] = value
            else:
                assert m.read_holding_registers(a, start, 10) == expected[a][start : start + 10]
        counters = bus.counters()  # type: ignore[attr-defined]
        assert counters.collisions == 0  # both sides kept the silences
        assert m.counters["frame_errors"] == m.counters["timeouts"] == 0
        # every slave sized the others' frames and took none of them for its own
        assert sum(s.counters["requests"] for s in slaves) == 150
        assert all(s.counters["bus_communication_error_count"] == 0 for s in slaves)


def test_ascii_shared_bus() -> None:
    with shared_bus(mode="ascii") as (m, _slaves, bus):
        for i in range(20):
            a = 1 + i % 3
            m.write_register(a, i, i * 7)
            assert m.read_holding_registers(a, i, 2) == [i * 7, 1000 + i + 1]
        assert bus.counters().collisions == 0  # type: ignore[attr-defined]


def test_echoing_drops() -> None:
    """The master's and slave 1's adapters echo: both read their own bytes back."""
    with shared_bus(echo=(0, 1)) as (m, slaves, bus):
        for i in range(20):
            m.write_register(1, i, i)  # FC 06: the slave's echo looks like a request
            assert m.read_holding_registers(1, i, 1) == [i]
            assert m.read_holding_registers(2, i, 1) == [1000 + i]
        m.write_register(0, 199, 5)
        assert m.read_holding_registers(1, 199, 1) == [5]
        assert m.counters["echo_mismatches"] == 0
        deadline = time.monotonic() + 1.0  # the last echo reaches slave 1 after the master
        while slaves[0].counters["echo_dropped"] < 41 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert slaves[0].counters["echo_dropped"] == 41
        assert slaves[0].counters["responses"] == 41
        assert bus.counters().collisions == 0  # type: ignore[attr-defined]


def test_broadcast_reaches_every_slave() -> None:
    with shared_bus(broadcast_delay=0.05) as (m, slaves, bus):
        m.write_registers(0, 100, [1, 2, 3])
        for a in (1, 2, 3):
            assert m.read_holding_registers(a, 100, 3) == [1, 2, 3]
        assert all(s.counters["broadcasts"] == 1 for s in slaves)
        assert bus.counters().collisions == 0  # type: ignore[attr-defined]


def test_noise_and_batching_give_typed_errors_never_wrong_values() -> None:
    faults = Faults(
        seed=11, bit_flip_rate=0.0005, drop_rate=0.001, insert_rate=0.001, batch_s=0.003
    )
    rng = random.Random(5)
    outcomes = {"ok": 0, "no_response": 0, "frame": 0}
    with shared_bus(faults=faults, timeout=0.25) as (m, _slaves, bus):
        for _ in range(240):
            a = rng.choice((1, 2, 3))
            start = rng.randrange(0, 100)
            try:
                values = m.read_holding_registers(a, start, 8)
            except NoResponseError:
                outcomes["no_response"] += 1
            except FrameError:
                outcomes["frame"] += 1
            else:
                assert values == [1000 + start + i for i in range(8)]  # never a wrong value
                outcomes["ok"] += 1
        faults_seen = bus.counters().faults  # type: ignore[attr-defined]
    assert faults_seen["bit_flips"] + faults_seen["dropped"] + faults_seen["inserted"] > 0
    assert outcomes["no_response"] + outcomes["frame"] > 0
    assert outcomes["ok"] > 150
    c = m.counters
    assert c["timeouts"] == outcomes["no_response"] and c["frame_errors"] == outcomes["frame"]


def test_retries_ride_through_noise() -> None:
    faults = Faults(seed=3, bit_flip_rate=0.0005, batch_s=0.003)
    with shared_bus(faults=faults, timeout=0.25, retries=3) as (m, _slaves, _bus):
        for i in range(60):
            try:
                assert m.read_holding_registers(1 + i % 3, i, 4) == [1000 + i + k for k in range(4)]
            except ModbusError as exc:  # four bad attempts in a row: rare, but typed
                assert isinstance(exc, NoResponseError | FrameError)
        assert m.counters["responses"] >= 55
