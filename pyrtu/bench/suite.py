"""The core against its pure-Python fallback and the peers installed here: CRC-16,
the framer, the stream parser, and a master's transaction on the virtual bus.

Each measurement is one `Row`: a group (what is measured), a contender (pyrtu's C
core, its pure-Python twin, a peer library), the figure (seconds per operation,
lower is better) and its spread.  Peers that are not installed are left out, and
said to be (``skipped``).  Nothing here asserts a speed: the user reads the table."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from pyrtu.bench.line import LineReport, check_serial
from pyrtu.bench.timer import CallTiming, percentile, time_call
from pyrtu.core._backend import backend
from pyrtu.drivers.master import Master

#: the sizes of the suite's inputs (the same as bench/bench_crc.py's and bench_core.py's
#: groups, so the figures can be set beside bench/RESULTS.md's)
CRC_SIZE = 256
STREAM_TRANSACTIONS = 2000
VBUS_BAUD = 115200
VBUS_REGISTERS = 10


@dataclass(frozen=True)
class Row:
    """One figure: ``seconds`` per ``unit`` of ``group`` for ``contender``."""

    group: str
    contender: str
    seconds: float
    low: float
    high: float
    unit: str
    extra: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "group": self.group,
            "contender": self.contender,
            "seconds": self.seconds,
            "low": self.low,
            "high": self.high,
            "unit": self.unit,
            **self.extra,
        }


@dataclass
class SuiteResult:
    rows: list[Row] = field(default_factory=list)
    #: (group, contender, why) of what could not be measured here
    skipped: list[tuple[str, str, str]] = field(default_factory=list)
    #: per transaction of the master on the virtual bus (seconds), for the histogram
    latencies: dict[str, list[float]] = field(default_factory=dict)
    #: the line check run against the virtual bus's slave (its time line)
    vbus_line: LineReport | None = None


def _row(group: str, contender: str, t: CallTiming, unit: str, **extra: float) -> Row:
    return Row(group, contender, t.median, t.low, t.high, unit, dict(extra))


def _backends() -> list[tuple[str, Any]]:
    out = []
    for name in ("c", "python"):
        try:
            out.append((name, backend(name)))
        except (ImportError, ValueError):
            continue
    return out


def _label(backend: str) -> str:
    return "pyrtu (C core)" if backend == "c" else "pyrtu (pure Python)"


# -- CRC ------------------------------------------------------------------------------


def _crc_peers() -> Iterator[tuple[str, Callable[[bytes], int] | None, str]]:
    """(name, crc function or None, why not)."""
    try:
        import crcmod.predefined  # type: ignore[import-untyped]

        yield "crcmod", crcmod.predefined.mkCrcFun("modbus"), ""
    except ImportError:
        yield "crcmod", None, "not installed"
    try:
        import minimalmodbus
    except ImportError:
        yield "minimalmodbus", None, "not installed"
    else:
        calc = getattr(minimalmodbus, "_calculate_crc", None)  # its internal (2.x)
        if calc is None:
            yield "minimalmodbus", None, "this version has no _calculate_crc"
        else:

            def mm(data: bytes) -> int:
                return int.from_bytes(calc(data), "little")

            yield "minimalmodbus", mm, ""


def crc(result: SuiteResult, budget: float) -> None:
    group = f"CRC-16 of {CRC_SIZE} bytes"
    data = bytes(range(256)) * (CRC_SIZE // 256) + bytes(CRC_SIZE % 256)
    expected = backend("python").crc16(data)
    for name, mod in _backends():
        t = time_call(functools.partial(mod.crc16, data), budget)
        result.rows.append(_row(group, _label(name), t, "call"))
    for name, peer, why in _crc_peers():
        if peer is None:
            result.skipped.append((group, name, why))
            continue
        if peer(data) != expected:  # a peer that computes something else is not compared
            result.skipped.append((group, name, "gives another CRC"))
            continue
        t = time_call(functools.partial(peer, data), budget)
        result.rows.append(_row(group, name, t, "call"))


# -- framer and stream parser ---------------------------------------------------------------


def _traffic(n: int) -> bytes:
    """``n`` transactions: a read of 10 holding registers and its answer, slaves 1..n."""
    out = bytearray()
    add = backend("python").add_crc
    for i in range(n):
        slave = 1 + i % 247
        out += add(bytes([slave, 3, 0, 0, 0, 10]))
        out += add(bytes([slave, 3, 20]) + bytes(range(20)))
    return bytes(out)


class _Feed:
    """One transaction into a framer, a transaction every 50 ms (so that silences end
    nothing early), its frames taken."""

    def __init__(self, framer: Any, data: bytes) -> None:
        self.framer, self.data, self.now = framer, data, 0.0

    def __call__(self) -> None:
        self.now += 0.05
        self.framer.receive_data(self.data, self.now)
        self.framer.events()


def framer(result: SuiteResult, budget: float) -> None:
    group = "framer: one transaction fed and framed"
    one = _traffic(1)
    for name, mod in _backends():
        feed = _Feed(mod.Framer("monitor", baudrate=19200), one)
        result.rows.append(_row(group, _label(name), time_call(feed, budget), "transaction"))


def stream(result: SuiteResult, budget: float) -> None:
    group = f"parse_stream: {STREAM_TRANSACTIONS} transactions"
    data = _traffic(STREAM_TRANSACTIONS)
    for name, mod in _backends():
        parse = mod.parse_stream
        frames = len(parse(data))
        if frames != 2 * STREAM_TRANSACTIONS:
            raise RuntimeError(
                f"parse_stream ({name}) found {frames} frames, not {2 * STREAM_TRANSACTIONS}"
            )
        t = time_call(functools.partial(parse, data), budget, min_batches=3)
        per = CallTiming(t.median / frames, t.low / frames, t.high / frames, t.batches, t.per_batch)
        result.rows.append(_row(group, _label(name), per, "frame"))


# -- a master's transaction on the virtual bus ----------------------------------------------

_SLAVE = """
import sys, pyrtu
store = pyrtu.DataStore()
store.holding_registers.add_range(0, list(range(100)))
with pyrtu.Slave(sys.argv[1], 1, store, baudrate=int(sys.argv[2]), parity="N") as slave:
    print("ready", flush=True)
    slave.serve_forever()
"""


@contextmanager
def _vbus_slave(baud: int) -> Iterator[str]:
    """A virtual bus of two drops: a pyrtu slave (another process) at 1 on drop 1;
    yields drop 0's path."""
    from pyrtu.vbus import VirtualBus

    with VirtualBus(2, baudrate=baud, parity="N") as bus:
        env = dict(os.environ)
        proc = subprocess.Popen(
            [sys.executable, "-c", _SLAVE, bus.paths[1], str(baud)],
            stdout=subprocess.PIPE,
            env=env,
            text=True,
        )
        try:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError("the virtual bus's slave did not start")
            yield bus.paths[0]
        finally:
            proc.terminate()
            proc.wait(5)


def _master_rounds(
    read: Callable[[], object], budget: float, result: SuiteResult, group: str, contender: str
) -> None:
    latencies: list[float] = []
    cpu: list[float] = []
    end = time.perf_counter() + budget
    while time.perf_counter() < end or len(latencies) < 20:
        c0, t0 = time.thread_time(), time.perf_counter()
        read()
        latencies.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    result.latencies[contender] = latencies
    t = CallTiming(percentile(latencies, 0.5), min(latencies), max(latencies), len(latencies), 1)
    result.rows.append(
        _row(
            group,
            contender,
            t,
            "transaction",
            p99=percentile(latencies, 0.99),
            cpu=percentile(cpu, 0.5),
            transactions=float(len(latencies)),
        )
    )


def master(result: SuiteResult, budget: float) -> None:
    group = f"master: read {VBUS_REGISTERS} registers, virtual bus at {VBUS_BAUD} baud"
    try:
        import pyrtu.vbus  # noqa: F401  (POSIX pseudo-terminals)
    except ImportError as exc:
        result.skipped.append((group, "every master", f"no virtual bus here: {exc}"))
        return
    with _vbus_slave(VBUS_BAUD) as port:
        for name, _mod in _backends():
            with Master(port, baudrate=VBUS_BAUD, parity="N", timeout=1, backend=name) as m:
                m.read_holding_registers(1, 0, VBUS_REGISTERS)  # the port open, warm

                def read(m: Any = m) -> object:
                    return m.read_holding_registers(1, 0, VBUS_REGISTERS)

                _master_rounds(read, budget, result, group, _label(name))
        _peer_masters(port, budget, result, group)
        result.vbus_line = check_serial(
            port,
            1,
            baudrate=VBUS_BAUD,
            parity="N",
            stopbits=1,
            bytesize=8,
            count=VBUS_REGISTERS,
            samples=50,
        )


def _peer_masters(port: str, budget: float, result: SuiteResult, group: str) -> None:
    try:
        import minimalmodbus
    except ImportError:
        result.skipped.append((group, "minimalmodbus", "not installed"))
    else:
        inst = minimalmodbus.Instrument(port, 1)
        inst.serial.baudrate = VBUS_BAUD
        inst.serial.timeout = 1
        inst.clear_buffers_before_each_transaction = True
        try:
            _master_rounds(
                functools.partial(inst.read_registers, 0, VBUS_REGISTERS),
                budget,
                result,
                group,
                "minimalmodbus",
            )
        finally:
            inst.serial.close()
    try:
        from pymodbus.client import ModbusSerialClient
    except ImportError:
        result.skipped.append((group, "pymodbus", "not installed"))
        return
    client = ModbusSerialClient(port, baudrate=VBUS_BAUD, parity="N", timeout=1)
    if not client.connect():
        result.skipped.append((group, "pymodbus", "could not open the port"))
        return
    try:
        unit = _pymodbus_unit_keyword(client)

        def read() -> object:
            keywords: dict[str, Any] = {"count": VBUS_REGISTERS, unit: 1}
            r = client.read_holding_registers(0, **keywords)
            if r.isError():
                raise RuntimeError(f"pymodbus: {r}")
            return r.registers

        _master_rounds(read, budget, result, group, "pymodbus")
    finally:
        client.close()  # type: ignore[no-untyped-call]


def _pymodbus_unit_keyword(client: Any) -> str:
    """pymodbus renamed ``slave=`` to ``device_id=`` (3.10)."""
    import inspect

    params = inspect.signature(client.read_holding_registers).parameters
    return "device_id" if "device_id" in params else "slave"


#: the suite's parts, in the order they run: name -> (what, function)
PARTS: dict[str, tuple[str, Callable[[SuiteResult, float], None]]] = {
    "crc": ("CRC-16", crc),
    "framer": ("the framer", framer),
    "stream": ("parse_stream", stream),
    "master": ("a master on the virtual bus", master),
}


def run_suite(
    parts: list[str], budget: float, progress: Callable[[str], None] | None = None
) -> SuiteResult:
    """Run ``parts`` (names of `PARTS`), each measurement ``budget`` seconds."""
    result = SuiteResult()
    for name in parts:
        what, fn = PARTS[name]
        if progress is not None:
            progress(what)
        fn(result, budget)
    return result


__all__ = ["PARTS", "Row", "SuiteResult", "run_suite"]
