"""Interoperability on the virtual bus (issue 4), 8N1 at 115200 baud with wire timing.

* the pyrtu Master against a pymodbus server and against a libmodbus server
  (every function each implements, exception responses, silence; ASCII with
  pymodbus);
* pymodbus, minimalmodbus and the libmodbus client against the pyrtu Slave
  (likewise, broadcasts, ASCII with pymodbus and minimalmodbus);
* a shared bus of three slaves (pyrtu, pymodbus, libmodbus) at 921600 baud: a
  broadcast reaching all three, then 10,000 transactions polled by the pyrtu
  Master with zero wrong answers, then the same with the bus's noise and batching
  on: every failure a typed pyrtu error, no wrong value.

Every value read is checked against the pattern of tests/peers/pattern.py (the
slave address is part of it, so an answer from the wrong slave is a wrong value).
The peers are separate programs: tests/peers/ (see tools.py), built and started by
the fixtures; libmodbus-dev is required (the fixture fails without it).
"""

from __future__ import annotations

import collections
import importlib.metadata
import json
import os
import random
import struct
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any

import pytest
from peers import pattern
from peers.tools import (
    Peer,
    PeerBinaries,
    libmodbus_script,
    libmodbus_server,
    minimal_instrument,
    pymodbus_client,
    pymodbus_server,
    pyrtu_slave_process,
)

from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import ExceptionResponseError, FrameError, ModbusError, NoResponseError
from pyrtu.protocol.datastore import DataStore
from pyrtu.vbus import Faults, VirtualBus

pytest_plugins = ["peers.fixtures"]

BAUD = 115200
TIMEOUT = 0.5
#: slave addresses: one per implementation, so the pattern tells them apart
PYRTU, PYMODBUS, LIBMODBUS = 7, 6, 5
SERVERS = {"pymodbus": PYMODBUS, "libmodbus": LIBMODBUS}


def open_master(port: str, **options: Any) -> Master:
    options.setdefault("timeout", TIMEOUT)
    return Master(port, BAUD, parity="N", stopbits=1, bytesize=8, **options)


@pytest.fixture
def bus() -> Iterator[VirtualBus]:
    """Two drops (0: client, 1: server), 8N1 timing at 115200 baud."""
    with VirtualBus(2, baudrate=BAUD, parity="N") as b:
        yield b


# ================================================================ pyrtu Master -> peers


@pytest.fixture(params=sorted(SERVERS))
def server(
    request: pytest.FixtureRequest, bus: VirtualBus, peer_binaries: PeerBinaries
) -> Iterator[tuple[str, int]]:
    """A server peer on drop 1: (name, slave address)."""
    name: str = request.param
    slave = SERVERS[name]
    if name == "pymodbus":
        peer = pymodbus_server(bus.paths[1], slave, baudrate=BAUD)
    else:
        peer = libmodbus_server(peer_binaries, bus.paths[1], slave, baudrate=BAUD)
    with peer:
        assert bus.wait_clients(1)
        yield name, slave
        assert peer.alive(), f"{name} died:\n{peer.log_tail()}"


def test_master_reads(server: tuple[str, int], bus: VirtualBus) -> None:
    _, s = server
    with open_master(bus.paths[0]) as m:
        for address, count in [(0, 1), (17, 10), (875, 125), (990, 10)]:
            assert m.read_holding_registers(s, address, count) == pattern.holdings(
                s, address, count
            )
            assert m.read_input_registers(s, address, count) == pattern.inputs(s, address, count)
        for address, count in [(0, 1), (3, 19), (0, 2000), (1990, 10), (1234, 77)]:
            assert m.read_coils(s, address, count) == pattern.coils(s, address, count)
            assert m.read_discrete_inputs(s, address, count) == pattern.discretes(s, address, count)
        assert m.counters["responses"] == 18


def test_master_writes(server: tuple[str, int], bus: VirtualBus) -> None:
    _, s = server
    with open_master(bus.paths[0]) as m:
        m.write_coil(s, 100, not pattern.coil(s, 100))
        assert m.read_coils(s, 99, 3) == [
            pattern.coil(s, 99),
            not pattern.coil(s, 100),
            pattern.coil(s, 101),
        ]
        m.write_register(s, 200, 0xBEEF)
        assert m.read_holding_registers(s, 199, 3) == [
            pattern.holding(s, 199),
            0xBEEF,
            pattern.holding(s, 201),
        ]
        bits = [True, False, True, True, False, False, True, False, True, True, True]
        m.write_coils(s, 300, bits)
        assert m.read_coils(s, 300, len(bits)) == bits
        words = list(range(1000, 1123))  # 123: the most FC 16 writes
        m.write_registers(s, 400, words)
        assert m.read_holding_registers(s, 400, 123) == words
        m.mask_write_register(s, 200, 0xF0F0, 0x0A0A)
        assert m.read_holding_registers(s, 200, 1) == [(0xBEEF & 0xF0F0) | (0x0A0A & ~0xF0F0)]
        # FC 23: the write happens before the read
        assert m.read_write_registers(s, 599, 4, 600, [1, 2, 3]) == [
            pattern.holding(s, 599),
            1,
            2,
            3,
        ]


@pytest.mark.wall_clock
def test_master_exceptions_and_no_response(server: tuple[str, int], bus: VirtualBus) -> None:
    _, s = server
    with open_master(bus.paths[0]) as m:
        t0 = time.monotonic()
        with pytest.raises(ExceptionResponseError) as info:
            m.read_holding_registers(s, 999, 2)  # crosses the end of the table
        # at once, not at the timeout: half of it (250 ms) is ~50x a pymodbus transaction
        # over the bus and above a loaded 2-core VM's stalls (tens of ms)
        assert time.monotonic() - t0 < TIMEOUT / 2, "an exception response returns at once"
        e = info.value
        assert (e.slave, e.function, e.code) == (s, 3, 2)
        assert isinstance(e, ModbusError)
        assert "ILLEGAL DATA ADDRESS" in e.name
        with pytest.raises(ExceptionResponseError) as info:
            m.write_register(s, 1000, 1)
        assert (info.value.function, info.value.code) == (6, 2)
        with pytest.raises(ExceptionResponseError) as info:
            m.read_coils(s, 1999, 2)
        assert (info.value.function, info.value.code) == (1, 2)
        # an address nobody serves: silence, typed
        t0 = time.monotonic()
        with pytest.raises(NoResponseError) as none:
            m.read_holding_registers(s + 100, 0, 1)
        assert time.monotonic() - t0 >= TIMEOUT * 0.9  # a lower bound: load only adds
        assert isinstance(none.value, TimeoutError) and isinstance(none.value, ModbusError)
        # and the server is still in step
        assert m.read_holding_registers(s, 10, 2) == pattern.holdings(s, 10, 2)
        c = m.counters
        assert c["exceptions"] == 3 and c["timeouts"] == 1


def test_master_report_server_id(server: tuple[str, int], bus: VirtualBus) -> None:
    name, s = server
    with open_master(bus.paths[0]) as m:
        data = m.report_server_id(s)
    if name == "libmodbus":
        # libmodbus 3.1: id 180 (a constant), run indicator ON, "LMB" + its version
        assert data[:5] == b"\xb4\xffLMB"
    else:
        # pymodbus: its identity objects joined by "-", then the run indicator
        assert data.startswith(b"pymodbus-peer-PYRTU-INTEROP-") and data.endswith(b"\xff")


def test_master_serial_line_functions_pymodbus(bus: VirtualBus) -> None:
    """FC 07, 08, 11, 12, 21, 24, 43 against pymodbus, which implements them."""
    s = PYMODBUS
    with pymodbus_server(bus.paths[1], s, baudrate=BAUD), open_master(bus.paths[0]) as m:
        assert bus.wait_clients(1)
        # Each answer decoded by the master is checked against the same answer taken
        # raw (Master.request) and decoded here with struct by the Application
        # Protocol's layout (6.7, 6.8, 6.9, 6.10, 6.18); pymodbus 3.16 does not count
        # (its counters stay 0), so the two calls see the same values.
        raw = m.request(s, b"\x07")  # 07, status
        assert raw[0] == 0x07 and len(raw) == 2
        assert m.read_exception_status(s) == raw[1] == 0
        assert m.diagnostics(s, 0x00, 0x1234) == 0x1234  # return query data
        raw = m.request(s, struct.pack(">BHH", 0x08, 0x0B, 0))  # 08, 000B, count
        assert struct.unpack(">BH", raw[:3]) == (0x08, 0x0B) and len(raw) == 5
        assert m.diagnostics(s, 0x0B) == struct.unpack(">H", raw[3:])[0] == 0
        raw = m.request(s, b"\x0b")  # 0B, status, event count
        assert raw[0] == 0x0B and len(raw) == 5
        assert m.get_comm_event_counter(s) == struct.unpack(">HH", raw[1:]) == (0, 0)
        raw = m.request(s, b"\x0c")  # 0C, byte count, status, events, messages, events
        assert raw[0] == 0x0C and raw[1] == len(raw) - 2 >= 6
        status, events, messages = struct.unpack(">HHH", raw[2:8])
        log = m.get_comm_event_log(s)
        assert (log.status, log.event_count, log.message_count) == (status, events, messages)
        assert log.events == list(raw[8:]) and (status, events, messages) == (0, 0, 0)
        raw = m.request(s, struct.pack(">BH", 0x18, 0))  # 18, byte count, count, values
        byte_count, count = struct.unpack(">HH", raw[1:5])
        assert raw[0] == 0x18 and byte_count == len(raw) - 3 == 2 + 2 * count
        values = list(struct.unpack(f">{count}H", raw[5:]))
        assert m.read_fifo_queue(s, 0) == values
        m.write_file_record(s, [(1, 0, [1, 2])])
        ident = m.read_device_identification(s)
        # the peer's identity (tests/peers/pymodbus_server.py): 2 is pymodbus's version
        version = importlib.metadata.version("pymodbus").encode()
        assert ident == {0: b"pymodbus-peer", 1: b"PYRTU-INTEROP", 2: version}
        assert m.read_device_identification(s, read_code=4, object_id=1) == {1: b"PYRTU-INTEROP"}
        # pymodbus 3.16 answers FC 20 with a dummy record whatever was asked: the
        # master must never hand that back as the records it asked for
        try:
            records = m.read_file_record(s, [(1, 0, 2)])
        except FrameError:
            pass
        else:
            assert [len(r) for r in records] == [2]
        assert m.read_holding_registers(s, 0, 3) == pattern.holdings(s, 0, 3)


@pytest.mark.wall_clock
def test_master_unsupported_functions_libmodbus(
    peer_binaries: PeerBinaries, bus: VirtualBus
) -> None:
    s = LIBMODBUS
    with libmodbus_server(peer_binaries, bus.paths[1], s), open_master(bus.paths[0]) as m:
        assert bus.wait_clients(1)
        for function in (0x41, 0x0B):  # a vendor code; FC 11, not in libmodbus
            t0 = time.monotonic()
            with pytest.raises(ExceptionResponseError) as info:
                m.execute(s, function, b"")
            assert (info.value.function, info.value.code) == (function, 1)
            # at once, not at the timeout (as above)
            assert time.monotonic() - t0 < TIMEOUT / 2
        # libmodbus 3.1 does not answer FC 07 at all, and frames FC 08/43 requests
        # as 4 bytes (bad CRC): silence, a typed error
        with pytest.raises(NoResponseError):
            m.read_exception_status(s)
        with pytest.raises(NoResponseError):
            m.diagnostics(s, 0, 0x1234)
        assert m.read_holding_registers(s, 0, 10) == pattern.holdings(s, 0, 10)


def test_master_ascii_against_pymodbus(bus: VirtualBus) -> None:
    """Modbus ASCII both sides (libmodbus has no ASCII)."""
    s = PYMODBUS
    with (
        pymodbus_server(bus.paths[1], s, baudrate=BAUD, mode="ascii"),
        open_master(bus.paths[0], mode="ascii") as m,
    ):
        assert bus.wait_clients(1)
        assert m.read_holding_registers(s, 875, 125) == pattern.holdings(s, 875, 125)
        assert m.read_discrete_inputs(s, 0, 2000) == pattern.discretes(s, 0, 2000)
        m.write_registers(s, 10, [0xABCD, 0x1234])
        assert m.read_holding_registers(s, 10, 2) == [0xABCD, 0x1234]
        with pytest.raises(ExceptionResponseError) as info:
            m.read_input_registers(s, 999, 2)
        assert info.value.code == 2
        with pytest.raises(NoResponseError):
            m.read_coils(s + 1, 0, 1)


# ================================================================ peers -> pyrtu Slave

IDENTIFICATION = {0: b"pyrtu-interop", 1: b"PYRTU", 2: b"0.1"}


def interop_store() -> DataStore:
    store = pattern.pattern_store(PYRTU)
    store.add_file(1, list(range(100, 120)))
    return store


@pytest.fixture
def pyrtu_slave(bus: VirtualBus) -> Iterator[Slave]:
    """An in-process pyrtu Slave on drop 1 (address PYRTU, spec timing)."""
    slave = Slave(
        bus.paths[1],
        address=PYRTU,
        store=interop_store(),
        baudrate=BAUD,
        parity="N",
        identification=dict(IDENTIFICATION),
    )
    slave.start()
    try:
        yield slave
    finally:
        slave.stop()
        slave.close()
    assert slave.error is None, slave.error


def test_pymodbus_client_against_pyrtu_slave(bus: VirtualBus, pyrtu_slave: Slave) -> None:
    from pymodbus.pdu.file_message import FileRecord

    s = PYRTU
    store = pyrtu_slave.store
    assert isinstance(store, DataStore)
    c = pymodbus_client(bus.paths[0], baudrate=BAUD, timeout=TIMEOUT)
    try:

        def ok(rr: Any) -> Any:
            assert not rr.isError(), rr
            return rr

        assert ok(c.read_coils(3, count=19, device_id=s)).bits[:19] == pattern.coils(s, 3, 19)
        assert ok(c.read_discrete_inputs(0, count=2000, device_id=s)).bits[:2000] == (
            pattern.discretes(s, 0, 2000)
        )
        assert ok(c.read_holding_registers(875, count=125, device_id=s)).registers == (
            pattern.holdings(s, 875, 125)
        )
        assert ok(c.read_input_registers(5, count=10, device_id=s)).registers == (
            pattern.inputs(s, 5, 10)
        )
        ok(c.write_coil(10, not pattern.coil(s, 10), device_id=s))
        assert store.coils.get(10) == (not pattern.coil(s, 10))
        ok(c.write_register(20, 0xCAFE, device_id=s))
        assert store.holding_registers.get(20) == 0xCAFE
        ok(c.write_coils(30, [True] * 9, device_id=s))
        assert [store.coils.get(a) for a in range(30, 39)] == [True] * 9
        ok(c.write_registers(40, [9, 8, 7], device_id=s))
        assert [store.holding_registers.get(a) for a in range(40, 43)] == [9, 8, 7]
        ok(c.mask_write_register(address=20, and_mask=0x00FF, or_mask=0x1200, device_id=s))
        assert store.holding_registers.get(20) == 0x12FE
        rr = ok(
            c.readwrite_registers(
                read_address=40, read_count=2, write_address=41, values=[5], device_id=s
            )
        )
        assert rr.registers == [9, 5]
        ok(c.read_exception_status(device_id=s))
        assert ok(c.diag_query_data(b"\x12\x34", device_id=s)).message == b"\x12\x34"
        assert ok(c.diag_read_bus_message_count(device_id=s)).message > 0
        ok(c.diag_get_comm_event_counter(device_id=s))
        ok(c.diag_get_comm_event_log(device_id=s))
        rr = ok(c.report_device_id(device_id=s))
        assert b"pyrtu" in rr.identifier
        # (no FC 24: pymodbus 3.16's client sizes the answer 2 bytes short,
        # ReadFifoQueueResponse.calculateRtuFrameSize, and fails even against pymodbus)
        read = FileRecord(file_number=1, record_number=2, record_length=6)  # bytes
        rr = ok(c.read_file_record([read], device_id=s))
        assert rr.records[0].record_data == b"".join(v.to_bytes(2, "big") for v in (102, 103, 104))
        write = FileRecord(file_number=1, record_number=5, record_data=b"\x00\x2a")
        ok(c.write_file_record([write], device_id=s))
        assert store.file(1).get(5) == 42
        rr = ok(c.read_device_information(read_code=1, object_id=0, device_id=s))
        assert {k: rr.information[k] for k in (0, 1, 2)} == IDENTIFICATION
        # exception paths
        rr = c.read_holding_registers(999, count=2, device_id=s)
        assert rr.isError() and rr.exception_code == 2
        rr = c.write_register(5000, 1, device_id=s)
        assert rr.isError() and rr.exception_code == 2
    finally:
        c.close()
    counters = pyrtu_slave.counters
    assert counters["exceptions"] == 2 and counters["requests"] == 21


def test_minimalmodbus_against_pyrtu_slave(bus: VirtualBus, pyrtu_slave: Slave) -> None:
    import minimalmodbus

    s = PYRTU
    store = pyrtu_slave.store
    assert isinstance(store, DataStore)
    inst = minimal_instrument(bus.paths[0], s, baudrate=BAUD, timeout=TIMEOUT)
    try:
        assert inst.read_register(5) == pattern.holding(s, 5)
        assert inst.read_registers(100, 125) == pattern.holdings(s, 100, 125)
        assert inst.read_registers(7, 3, functioncode=4) == pattern.inputs(s, 7, 3)
        assert inst.read_bits(3, 40, functioncode=1) == [int(b) for b in pattern.coils(s, 3, 40)]
        assert inst.read_bit(4, functioncode=2) == int(pattern.discrete(s, 4))
        inst.write_register(50, 4321, functioncode=6)
        inst.write_registers(60, [1, 2, 3])
        assert inst.read_registers(50, 1) + inst.read_registers(60, 3) == [4321, 1, 2, 3]
        inst.write_bit(70, 1, functioncode=5)
        inst.write_bits(71, [1, 0, 1])
        assert [store.coils.get(a) for a in range(70, 74)] == [True, True, False, True]
        inst.write_long(80, 0x12345678)
        assert store.holding_registers.get_many(80, 2) == [0x1234, 0x5678]
        assert inst.read_long(80) == 0x12345678
        inst.write_float(90, 3.5)
        assert inst.read_float(90) == 3.5
        inst.write_string(100, "pyrtu!", number_of_registers=3)
        assert inst.read_string(100, 3) == "pyrtu!"
        with pytest.raises(minimalmodbus.IllegalRequestError):  # exception 2
            inst.read_registers(999, 2)
        assert inst.read_register(1) == pattern.holding(s, 1)
    finally:
        inst.serial.close()


def test_libmodbus_client_against_pyrtu_slave(
    peer_binaries: PeerBinaries, bus: VirtualBus, pyrtu_slave: Slave
) -> None:
    s = PYRTU
    store = pyrtu_slave.store
    assert isinstance(store, DataStore)
    ops = [
        "r01:3:10",
        "r02:0:2000",
        "r03:875:125",
        "r04:998:2",
        "w05:3:1",
        "w06:5:1234",
        "w15:10:1,0,1,1",
        "w16:20:1,2,3",
        "m22:20:0xff00:0x0011",
        "rw23:20:2:30:7,8",
        "r03:30:2",
        "id17",
        "r03:999:2",
        "raw:4100",  # a function the slave does not have: exception 1
        "raw:07",  # read exception status (FC 08, 11, 12, 24 answers libmodbus cannot size)
        "slave:0",
        "w06:6:99",  # broadcast: executed, not answered (libmodbus waits: timeout)
    ]
    # 1 s: a loaded runner may hold the slave past a few hundred ms (the broadcast op waits it out)
    r = libmodbus_script(peer_binaries, bus.paths[0], s, ops, baudrate=BAUD, timeout_ms=1000)
    assert r[0]["values"] == pattern.coils(s, 3, 10)
    assert r[1]["values"] == pattern.discretes(s, 0, 2000)
    assert r[2]["values"] == pattern.holdings(s, 875, 125)
    assert r[3]["values"] == pattern.inputs(s, 998, 2)
    assert all(x["ok"] for x in r[4:12]), r[4:12]
    assert store.coils.get(3) is True
    assert store.holding_registers.get(5) == 1234
    assert [store.coils.get(a) for a in range(10, 14)] == [True, False, True, True]
    assert r[9]["values"] == [(1 & 0xFF00) | 0x0011, 2]
    assert r[10]["values"] == [7, 8]
    assert bytes.fromhex(r[11]["pdu"]).startswith(b"pyrtu")
    assert r[12] == {"op": "r03:999:2", "ok": False, "exception": 2}
    assert r[13]["pdu"] == "c101"
    assert r[14]["pdu"] == "0700"  # FC 07: the slave's exception status bits, all clear
    assert r[16]["ok"] is False and "exception" not in r[16]  # no answer to a broadcast
    assert store.holding_registers.get(6) == 99


def test_peer_broadcasts_to_pyrtu_slave(bus: VirtualBus, pyrtu_slave: Slave) -> None:
    """minimalmodbus and pymodbus broadcast writes (address 0): executed, not answered."""
    store = pyrtu_slave.store
    assert isinstance(store, DataStore)
    inst = minimal_instrument(bus.paths[0], 0, baudrate=BAUD, timeout=TIMEOUT)
    try:
        inst.write_register(3, 4242)  # minimalmodbus does not wait for an answer at 0
    finally:
        inst.serial.close()
    c = pymodbus_client(bus.paths[0], baudrate=BAUD, timeout=TIMEOUT)
    try:
        c.write_registers(4, [43, 44], device_id=0, no_response_expected=True)
    finally:
        c.close()
    deadline = time.monotonic() + 2
    while pyrtu_slave.counters["broadcasts"] < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert store.holding_registers.get_many(3, 3) == [4242, 43, 44]
    counters = pyrtu_slave.counters
    assert counters["broadcasts"] == 2 and counters["responses"] == 0


def test_peer_clients_ascii_against_pyrtu_slave(bus: VirtualBus) -> None:
    """pymodbus and minimalmodbus in Modbus ASCII against the pyrtu Slave in ASCII."""
    s = PYRTU
    store = interop_store()
    with Slave(
        bus.paths[1], address=s, store=store, baudrate=BAUD, parity="N", mode="ascii"
    ) as slave:
        slave.start()
        c = pymodbus_client(bus.paths[0], baudrate=BAUD, timeout=TIMEOUT, mode="ascii")
        try:
            rr = c.read_holding_registers(100, count=125, device_id=s)
            assert rr.registers == pattern.holdings(s, 100, 125)
            assert not c.write_register(3, 777, device_id=s).isError()
            rr = c.read_coils(1000, count=99, device_id=s)
            assert rr.bits[:99] == pattern.coils(s, 1000, 99)
            rr = c.read_input_registers(999, count=2, device_id=s)
            assert rr.isError() and rr.exception_code == 2
        finally:
            c.close()
        assert store.holding_registers.get(3) == 777
        inst = minimal_instrument(bus.paths[0], s, baudrate=BAUD, timeout=TIMEOUT, mode="ascii")
        try:
            assert inst.read_registers(3, 2) == [777, pattern.holding(s, 4)]
            inst.write_float(20, -1.25)
            assert inst.read_float(20) == -1.25
            assert inst.read_bits(5, 11, functioncode=2) == [
                int(b) for b in pattern.discretes(s, 5, 11)
            ]
        finally:
            inst.serial.close()
        slave.stop()
        assert slave.error is None, slave.error


# ================================================================ shared bus


@dataclass
class Tally:
    """Outcomes of a polling run."""

    ok: int = 0
    wrong: list[str] = field(default_factory=list)
    errors: collections.Counter[str] = field(default_factory=collections.Counter)
    untyped: list[str] = field(default_factory=list)
    #: seconds per answered transaction, per slave
    times: dict[str, list[float]] = field(default_factory=lambda: collections.defaultdict(list))

    @property
    def failed(self) -> int:
        return sum(self.errors.values())

    def summary(self) -> str:
        lines = [f"ok={self.ok} wrong={len(self.wrong)} errors={dict(self.errors)}"]
        for name, times in sorted(self.times.items()):
            t = sorted(times)
            lines.append(
                f"  {name}: {len(t)} answered, ms median {t[len(t) // 2] * 1e3:.2f} "
                f"p99 {t[int(len(t) * 0.99)] * 1e3:.2f} max {t[-1] * 1e3:.2f}"
            )
        return "\n".join(lines)


#: polls in a row to one slave before the next (SCADA-style: a few blocks of one
#: device, then the next device).  Every slave still sees the other slaves'
#: traffic between its bursts; pymodbus misses mostly the first poll of a burst.
BURST = 3


def poll(master: Master, slaves: dict[str, int], n: int, seed: int, writes: bool) -> Tally:
    """n transactions, round-robin over the slaves in bursts, every value checked.

    A seeded mix: 55 % FC 03, 20 % FC 04, 15 % FC 01, 10 % FC 02 at random addresses
    and counts; with ``writes``, a tenth of the FC 03 share (5 % of all) are FC 16
    writes of the pattern's own values instead.
    """
    rng = random.Random(seed)
    names = sorted(slaves)
    tally = Tally()
    for i in range(n):
        name = names[(i // BURST) % len(names)]
        s = slaves[name]
        kind = rng.random()
        t0 = time.perf_counter()
        try:
            if writes and kind < 0.05:  # write the pattern's own values back (idempotent)
                address, count = rng.randrange(0, 980), rng.randint(1, 20)
                master.write_registers(s, address, pattern.holdings(s, address, count))
                tally.ok += 1
                tally.times[name].append(time.perf_counter() - t0)
                continue
            if kind < 0.55:
                address, count = rng.randrange(0, 990), rng.randint(1, 10)
                got: list[Any] = master.read_holding_registers(s, address, count)
                want: list[Any] = pattern.holdings(s, address, count)
            elif kind < 0.75:
                address, count = rng.randrange(0, 990), rng.randint(1, 10)
                got, want = (
                    master.read_input_registers(s, address, count),
                    pattern.inputs(s, address, count),
                )
            elif kind < 0.9:
                address, count = rng.randrange(0, 1900), rng.randint(1, 80)
                got, want = master.read_coils(s, address, count), pattern.coils(s, address, count)
            else:
                address, count = rng.randrange(0, 1900), rng.randint(1, 80)
                got = master.read_discrete_inputs(s, address, count)
                want = pattern.discretes(s, address, count)
        except ModbusError as exc:
            if not isinstance(exc, NoResponseError | FrameError | ExceptionResponseError):
                tally.untyped.append(repr(exc))
            tally.errors[f"{name}:{type(exc).__name__}"] += 1
            continue
        tally.times[name].append(time.perf_counter() - t0)
        if got == want:
            tally.ok += 1
        else:
            tally.wrong.append(f"#{i} {name} ({s}) @{address}x{count}: got {got}, want {want}")
    return tally


SHARED = {"pyrtu": PYRTU, "pymodbus": PYMODBUS, "libmodbus": LIBMODBUS}
#: the highest standard rate the peers configure; the bus keeps wire timing at it
SHARED_BAUD = 921600
#: 10,000 as the issue asks (PYRTU_INTEROP_TRANSACTIONS overrides it for a quick local run)
TRANSACTIONS = int(os.environ.get("PYRTU_INTEROP_TRANSACTIONS", "10000"))
#: the master's timeout on the shared bus: well above every slave's answer time
#: (about 2-5 ms; the printed times of a transaction that follows a failure include
#: the master's 20 ms settling silence), and above the libmodbus server's wait for
#: another slave's answer (LIBMODBUS_ARGS), so that wait never swallows a request.
#: Every pymodbus miss costs it, and the test's duration is mostly those.
SHARED_TIMEOUT = 0.025
LIBMODBUS_ARGS = ("--response-timeout-ms", "15", "--byte-timeout-ms", "10")


@dataclass
class SharedBus:
    bus: VirtualBus
    peers: dict[str, Peer]


@pytest.fixture
def shared_bus(request: pytest.FixtureRequest, peer_binaries: PeerBinaries) -> Iterator[SharedBus]:
    """Drop 0: the master; drops 1-3: pyrtu, pymodbus and libmodbus slaves (own processes)."""
    faults: Faults | None = getattr(request, "param", None)
    with ExitStack() as stack:
        bus = stack.enter_context(VirtualBus(4, baudrate=SHARED_BAUD, parity="N", faults=faults))
        peers = {
            "pyrtu": pyrtu_slave_process(bus.paths[1], PYRTU, baudrate=SHARED_BAUD),
            "pymodbus": pymodbus_server(bus.paths[2], PYMODBUS, baudrate=SHARED_BAUD),
            "libmodbus": libmodbus_server(
                peer_binaries, bus.paths[3], LIBMODBUS, baudrate=SHARED_BAUD, args=LIBMODBUS_ARGS
            ),
        }
        for peer in peers.values():
            stack.enter_context(peer)
        for drop in (1, 2, 3):
            assert bus.wait_clients(drop)
        yield SharedBus(bus, peers)


def report(
    shared: SharedBus, master: Master, tally: Tally, seconds: float
) -> tuple[str, dict[str, Any]]:
    """What happened, and the pyrtu slave's counters (the peers are stopped here)."""
    died = [f"{name} died:\n{p.log_tail()}" for name, p in shared.peers.items() if not p.alive()]
    assert not died, "\n".join(died)
    stats = {name: peer.stop() for name, peer in shared.peers.items()}
    slave_counters: dict[str, Any] = json.loads(stats["pyrtu"] or "{}")
    counters = shared.bus.counters()
    lines = [
        f"{tally.ok + tally.failed} transactions in {seconds:.1f} s: {tally.summary()}",
        f"master counters: {json.dumps(master.counters)}",
        f"bus: wire_bytes={counters.wire_bytes} collisions={counters.collisions} "
        f"faults={counters.faults}",
        *(f"{name} stats: {line}" for name, line in stats.items()),
    ]
    return "\n".join(lines), slave_counters


def test_shared_bus_three_slaves(shared_bus: SharedBus, capsys: pytest.CaptureFixture[str]) -> None:
    """10,000 transactions, zero wrong answers, and the pyrtu slave never misses one
    that reached it intact.

    The pyrtu slave's own counters must show every request for it recognised and
    answered, and no frame on the bus it could not size.  On the master's side a
    handful of its answers may come after the 25 ms timeout when the machine is
    loaded (5 processes on the bus), or meet a pymodbus stray answer (below); they
    count as typed misses, at most 0.1 %.

    The peers are not shared-bus citizens, and their misses are counted (printed)
    and must be typed `NoResponseError`s, never a wrong value:

    * pymodbus 3.16's RTU framer has no inter-frame timing: it parses other slaves'
      responses as requests, drops what fails the CRC, and when the leftovers look
      like the start of a long request it waits, then discards the next real
      request with them (about a third of the polls that follow other slaves'
      traffic, mostly the first of each burst here).
    * libmodbus 3.1 sizes the frame after a request for another slave as that
      slave's response (``confirmation_to_ignore``): when pymodbus stays silent it
      takes the next request for that response (a few percent of its polls).
    * pymodbus also answers some frames it cannot decode (other slaves' responses
      read as requests) with exception 1 under the other slave's address and
      function 0x80 ("stray" in its stats): the master must drop those.
    """
    bus = shared_bus.bus
    with open_master(bus.paths[0], timeout=SHARED_TIMEOUT) as master:
        assert master.t35 == pytest.approx(0.00175)  # the spec's timing above 19200 baud
        t0 = time.monotonic()
        tally = poll(master, SHARED, TRANSACTIONS, seed=10_000, writes=True)
        seconds = time.monotonic() - t0
        text, slave = report(shared_bus, master, tally, seconds)
    with capsys.disabled():
        print("\n" + text)
    assert not tally.wrong, "\n".join(tally.wrong[:20]) + "\n" + text
    assert not tally.untyped, text
    assert tally.ok + tally.failed == TRANSACTIONS
    polls = TRANSACTIONS // len(SHARED)
    # Every request that reached it intact: on a loaded machine an answer can come
    # after the master's 25 ms timeout and collide with the next request, which no
    # slave can read (the bus counts the collisions; each spoils at most one frame).
    collisions = bus.counters().collisions
    assert slave["requests"] == slave["responses"] == slave["slave_message_count"], text
    assert slave["requests"] >= polls - collisions, text
    # every intact frame sized, CRC good
    assert slave["bus_communication_error_count"] <= collisions, text
    pyrtu_misses = sum(n for k, n in tally.errors.items() if k.startswith("pyrtu:"))
    assert pyrtu_misses <= polls // 1000, text
    # (a FrameError would be a pymodbus stray answer colliding with a real one)
    assert {k.split(":")[1] for k in tally.errors} <= {"NoResponseError", "FrameError"}, text
    for name in SHARED:  # a sanity floor: every peer is up and in step most of the time
        assert len(tally.times[name]) > polls // 4, text


def test_shared_bus_broadcast(shared_bus: SharedBus) -> None:
    """A broadcast write reaches all three slaves, none answers, each executes it.

    (Retries for the reads: pymodbus misses polls on a shared bus, see below.)
    """
    bus = shared_bus.bus
    with open_master(bus.paths[0], timeout=SHARED_TIMEOUT, retries=5) as master:
        master.write_register(0, 123, 0xABCD)
        master.write_registers(0, 124, [1, 2, 3])
        master.write_coils(0, 7, [True, True, False])
        for name, s in SHARED.items():
            assert master.read_holding_registers(s, 122, 5) == [
                pattern.holding(s, 122),
                0xABCD,
                1,
                2,
                3,
            ], name
            assert master.read_coils(s, 7, 3) == [True, True, False], name
        c = master.counters
    assert c["broadcasts"] == 3 and c["responses"] == 6 and c["discarded_bytes"] == 0, c
    assert bus.counters().collisions == 0


NOISE = Faults(
    seed=4,
    bit_flip_rate=2e-4,  # per bit; with the lost and inserted bytes, ~5 % of transactions hit
    drop_rate=5e-4,  # per byte
    insert_rate=5e-4,  # per byte
    batch_s=0.0005,  # every drop receives in bursts, as through a USB adapter
    batch_bytes=16,
)


@pytest.mark.parametrize("shared_bus", [NOISE], indirect=True, ids=["noise+batching"])
def test_shared_bus_noise_and_batching(
    shared_bus: SharedBus, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same bus with bit flips, lost and inserted bytes and batched delivery on.

    Every failure is a typed pyrtu error, no wrong value is ever returned, and the
    faults really were injected (the errors and the bus's fault counters say so).
    """
    bus = shared_bus.bus
    with open_master(bus.paths[0], timeout=SHARED_TIMEOUT) as master:
        t0 = time.monotonic()
        tally = poll(master, SHARED, TRANSACTIONS, seed=4, writes=False)
        seconds = time.monotonic() - t0
        text, slave_counters = report(shared_bus, master, tally, seconds)
    with capsys.disabled():
        print("\n" + text)
    faults = bus.counters().faults
    assert not tally.wrong, "\n".join(tally.wrong[:20]) + "\n" + text
    assert not tally.untyped, text
    assert tally.ok + tally.failed == TRANSACTIONS
    assert faults["bit_flips"] > 0 and faults["dropped"] > 0 and faults["inserted"] > 0, text
    assert faults["batches"] > 0, text
    assert master.counters["crc_errors"] > 0, text
    assert tally.failed > 0, "the faults surfaced as errors"
    for slave in ("pyrtu", "libmodbus"):
        assert tally.errors[f"{slave}:FrameError"] + tally.errors[f"{slave}:NoResponseError"] > 0
    assert tally.ok > TRANSACTIONS // 2, text
    # the pyrtu slave saw damaged frames, stayed silent for them, answered the rest
    assert slave_counters["bus_communication_error_count"] > 0, text
    assert slave_counters["requests"] == slave_counters["responses"], text
