"""The slave at the byte level: silence where the spec wants it, shared-bus framing,
FC 08 counters (Bonfiglioli 6.4.5 / 8.1.5), listen-only mode, event counter and log,
several addresses, custom functions, hooks, stop()."""

from __future__ import annotations

import time
from collections.abc import Iterator
from types import ModuleType

import pytest
from ptylink import PtyLink, RawPort, make_store, rtu, serving
from waiting import ANSWER_TIMEOUT, SILENCE_TIMEOUT

from pyrtu import encode_ascii
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import ExceptionResponseError, NoResponseError, SlaveException
from pyrtu.protocol.datastore import DataStore


@pytest.fixture
def link() -> Iterator[PtyLink]:
    with PtyLink() as pty:
        yield pty


def test_silent_for_other_addresses_bad_crc_and_broadcasts(
    link: PtyLink, backend: ModuleType
) -> None:
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0, backend=backend.BACKEND) as s,
        RawPort(link.path_a) as port,
    ):
        assert port.ask(rtu("01 03 0000 0001"), want=7) == rtu("01 03 02 03E8")
        assert port.ask(rtu("02 03 0000 0001")) == b""  # another slave's request
        bad = bytearray(rtu("01 06 0000 0063"))
        bad[-1] ^= 0xFF
        assert port.ask(bytes(bad)) == b""  # bad CRC: silent, not executed
        assert port.ask(rtu("00 06 0000 0063")) == b""  # broadcast: executed, silent
        assert s.store_for(1).holding_registers.get(0) == 0x63
        assert port.ask(rtu("00 03 0000 0001")) == b""  # a broadcast read: ignored
        c = s.counters
        assert c["requests"] == 1 and c["broadcasts"] == 2 and c["ignored"] == 1
        assert c["bus_communication_error_count"] == 1
        assert c["bus_message_count"] == 4
        assert c["slave_message_count"] == 3
        assert c["slave_no_response_count"] == 2


def test_other_slaves_answers_are_never_taken_for_requests(
    link: PtyLink, backend: ModuleType
) -> None:
    """Slave 7's answer carries, inside its data, a valid write request to us. On a bus
    read byte by byte (or batched in one chunk) the framer sizes the answer as a
    response and the slave never executes what is inside it."""
    hidden = rtu("01 06 0000 002A")  # 8 bytes: a valid FC 06 request to slave 1
    assert len(hidden) == 8
    answer = rtu("07 03 08" + hidden.hex())  # slave 7 answers 4 registers: the same bytes
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0, backend=backend.BACKEND) as s,
        RawPort(link.path_a) as port,
    ):
        request = rtu("07 03 0000 0004")
        port.send(request + answer)  # batched together, as a USB adapter delivers them
        assert port.collect() == b""
        port.send(request)
        time.sleep(0.01)
        for i in range(len(answer)):  # and one byte at a time
            port.send(answer[i : i + 1])
        assert port.collect() == b""
        assert s.store_for(1).holding_registers.get(0) == 1000
        assert s.counters["bus_message_count"] == 4
        assert s.counters["requests"] == 0
        assert port.ask(rtu("01 03 0000 0001"), want=7) == rtu("01 03 02 03E8")


def test_bonfiglioli_diagnostic_counter_examples(link: PtyLink, backend: ModuleType) -> None:
    """ACT/ACU manual 8.1.5: the exact telegrams of examples 1a, 1b and 2."""
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0, backend=backend.BACKEND),
        RawPort(link.path_a) as port,
    ):
        port.ask(rtu("01 03 0000 0001"), want=7)
        clear = bytes.fromhex("01 08 00 0A 00 00 C0 09")
        assert port.ask(clear, want=8) == clear
        assert port.ask(bytes.fromhex("01 08 00 0E 00 00 81 C8"), want=8) == bytes.fromhex(
            "01 08 00 0E 00 01 40 08"
        )
        assert port.ask(bytes.fromhex("01 08 00 13 00 00 11 CE"), want=5) == bytes.fromhex(
            "01 88 01 87 C0"
        )


def test_diagnostic_counters(link: PtyLink, backend: ModuleType) -> None:
    be = backend.BACKEND
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0, backend=be, max_adu=64) as s,
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT, backend=be) as m,
        RawPort(link.path_a) as raw,
    ):
        assert m.diagnostics(1, 0x0A) == 0
        raw.send(rtu("05 03 0000 0001"))  # a request to another slave
        raw.send(rtu("05 03 02 0000"))  # and its answer
        bad = bytearray(rtu("01 03 0000 0001"))
        bad[3] ^= 1
        raw.send(bytes(bad))  # a CRC error
        time.sleep(0.1)  # more than the 71 bytes below take at 19200 baud: two messages
        raw.send(rtu("01 10 0000 0020 40" + "0000" * 32))  # 71 bytes > max_adu 64: overrun
        time.sleep(0.1)
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(1, 900, 1)  # an exception answered
        m.write_register(0, 0, 1)  # a broadcast: no response
        time.sleep(0.15)
        counts = {sub: m.diagnostics(1, sub) for sub in range(0x0B, 0x13)}
        assert (
            counts[0x0B] == 5
        )  # 2 foreign frames, exception, broadcast, this (clear zeroed itself)
        assert counts[0x0C] == 2  # the CRC error and the overrun
        assert counts[0x0D] == 1  # one exception answered
        assert counts[0x0E] == 6  # exception request, broadcast, 0x0B, 0x0C, 0x0D, this
        assert counts[0x0F] == 1  # the broadcast
        assert counts[0x10] == 0 and counts[0x11] == 0
        assert counts[0x12] == 1  # the overrun
        assert m.diagnostics(1, 0x14) == 0  # clear overrun counter
        assert m.diagnostics(1, 0x12) == 0
        assert m.diagnostics(1, 0x02) == 0  # diagnostic register
        with pytest.raises(ExceptionResponseError) as info:
            m.diagnostics(1, 0x0B, 1)  # data must be 0
        assert info.value.code == 3
        assert s.counters["slave_exception_error_count"] == 2


def test_listen_only_and_restart(link: PtyLink, backend: ModuleType) -> None:
    be = backend.BACKEND
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0, backend=be) as s,
        Master(link.path_a, parity="N", t35=0, timeout=SILENCE_TIMEOUT, backend=be) as m,
    ):
        assert m.diagnostics(1, 0x04) == 0  # force listen only: no answer awaited
        time.sleep(0.05)
        assert s.listen_only
        with pytest.raises(NoResponseError):
            m.read_holding_registers(1, 0, 1)
        with pytest.raises(NoResponseError):
            m.write_register(1, 0, 77)
        assert s.store_for(1).holding_registers.get(0) == 1000  # not executed
        with pytest.raises(NoResponseError):  # restart from listen-only: no answer either
            m.diagnostics(1, 0x01, 0xFF00)
        assert not s.listen_only
        assert m.read_holding_registers(1, 0, 1) == [1000]
        log = m.get_comm_event_log(1)
        assert log.events[-1] == 0x00  # the restart (log cleared by 0xFF00) ...
        assert log.events[:4] == [0x80, 0x40, 0x80, 0x00]
        assert m.diagnostics(1, 0x01) == 0  # restart when not listening: answered
        with pytest.raises(ExceptionResponseError):
            m.diagnostics(1, 0x01, 0x1234)


def test_event_counter_and_log(link: PtyLink) -> None:
    with (
        serving(link.path_b, address=1, store=make_store(), t35=0) as s,
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT) as m,
    ):
        assert m.get_comm_event_counter(1) == (0, 0)
        m.read_holding_registers(1, 0, 1)
        m.write_register(1, 0, 1)
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(1, 999, 1)
        assert m.get_comm_event_counter(1) == (0, 2)  # exceptions and FC 11 not counted
        s.busy = True
        status, count = m.get_comm_event_counter(1)
        assert (status, count) == (0xFFFF, 2)
        s.busy = False
        log = m.get_comm_event_log(1)
        assert log.event_count == 2
        assert log.message_count == 7
        # newest first: receive (this), send (FC 11), receive, send, receive,
        # send with exception bit 0 (code 2), receive, ...
        assert log.events[:7] == [0x80, 0x40, 0x80, 0x40, 0x80, 0x41, 0x80]


def test_several_addresses_and_stores(link: PtyLink) -> None:
    stores = {1: DataStore(), 2: DataStore()}
    stores[1].holding_registers.add_range(0, [11])
    stores[2].holding_registers.add_range(0, [22])
    with (
        serving(link.path_b, address={1, 2}, store=stores, t35=0),
        Master(link.path_a, parity="N", t35=0, timeout=SILENCE_TIMEOUT) as m,
    ):
        assert m.read_holding_registers(1, 0, 1) == [11]
        assert m.read_holding_registers(2, 0, 1) == [22]
        with pytest.raises(NoResponseError):
            m.read_holding_registers(3, 0, 1)
        m.write_register(0, 0, 5)  # broadcast reaches both stores
        assert m.read_holding_registers(1, 0, 1) == [5]
        assert m.read_holding_registers(2, 0, 1) == [5]
    with pytest.raises(ValueError, match="no DataStore"):
        Slave(link.path_b, address={1, 3}, store=stores, parity="N")
    with pytest.raises(ValueError, match=r"1\.\.247"):
        Slave(link.path_b, address=0, parity="N")


def test_supported_functions_hooks_and_custom_handlers(link: PtyLink) -> None:
    seen: list[tuple[int, bytes]] = []

    def hook(unit: int, pdu: bytes) -> None:
        seen.append((unit, pdu))
        if pdu[:1] == b"\x06" and pdu[1:3] == b"\x00\x63":
            raise SlaveException(6)  # busy

    def echo_upper(slave: Slave, unit: int, pdu: bytes) -> bytes:
        return pdu[:1] + pdu[1:].upper()

    def silent(slave: Slave, unit: int, pdu: bytes) -> None:
        return None

    def broken(slave: Slave, unit: int, pdu: bytes) -> bytes:
        raise KeyError("bug")

    with (
        serving(link.path_b, store=make_store(), t35=0, functions={3, 6}) as s,
        Master(link.path_a, parity="N", t35=0, timeout=SILENCE_TIMEOUT) as m,
    ):
        s.on_request(hook)
        s.register_function(0x46, echo_upper)
        s.register_function(0x47, silent)
        s.register_function(0x48, broken)
        assert m.read_holding_registers(1, 0, 1) == [1000]
        with pytest.raises(ExceptionResponseError) as info:
            m.read_coils(1, 0, 1)  # not among functions
        assert info.value.code == 1
        with pytest.raises(ExceptionResponseError) as info:
            m.write_register(1, 0x63, 1)
        assert info.value.code == 6
        assert s.counters["slave_busy_count"] == 1
        assert m.execute(1, 0x46, b"abc") == b"ABC"
        with pytest.raises(NoResponseError):
            m.execute(1, 0x47, b"")
        with pytest.raises(ExceptionResponseError) as info:
            m.execute(1, 0x48, b"")
        assert info.value.code == 4
        assert [pdu[0] for _unit, pdu in seen] == [3, 1, 6, 0x46, 0x47, 0x48]
    with pytest.raises(ValueError, match=r"1\.\.127"):
        s.register_function(0x80, echo_upper)


@pytest.mark.wall_clock
def test_stop_is_prompt(link: PtyLink) -> None:
    slave = Slave(link.path_b, parity="N")
    slave.start()
    time.sleep(0.05)
    start = time.monotonic()
    slave.stop()
    # Slave.stop returns within the serving loop's poll interval (50 ms, its
    # documented promise; the loop's wait for bytes is that long at most): 4 of them
    # leave 150 ms for a loaded 2-core VM to schedule the thread.
    poll_interval = 0.05
    assert time.monotonic() - start < 4 * poll_interval
    with pytest.raises(RuntimeError, match="already"):
        slave.start().start()
    slave.close()
    assert slave.error is None


def test_serve_forever_in_the_caller(link: PtyLink) -> None:
    import threading

    slave = Slave(link.path_b, store=make_store(), parity="N", t35=0)
    results: list[list[int]] = []
    with Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT) as m:

        def client() -> None:
            try:
                results.append(m.read_holding_registers(1, 0, 1))
            finally:
                slave.stop()

        threading.Timer(0.05, client).start()
        slave.serve_forever()  # returns when stop() is called
        assert results == [[1000]]
    slave.close()


def test_ascii_delimiter_and_inter_character_limit(link: PtyLink) -> None:
    with (
        serving(link.path_b, store=make_store(), mode="ascii") as s,
        RawPort(link.path_a) as port,
    ):
        request = encode_ascii(bytes.fromhex("01 03 0000 0001"))
        answer = encode_ascii(bytes.fromhex("01 03 02 03E8"))
        assert port.ask(request, want=len(answer)) == answer
        # a pause over one second inside a frame discards it (Serial Line 2.5.2.1)
        port.send(request[:5])
        time.sleep(1.1)
        port.send(request[5:])
        assert port.collect() == b""
        # FC 08 sub-function 0x03: '!' ends frames from now on
        change = encode_ascii(bytes.fromhex("01 08 0003 2100"))
        assert port.ask(change, want=len(change)) == change
        assert s.line.ascii_delimiter == 0x21
        assert port.ask(request) == b""  # CR LF no longer ends a frame
        assert port.ask(request[:-1] + b"!", want=len(answer)) == answer
        restart = encode_ascii(bytes.fromhex("01 08 0001 0000"))
        assert port.ask(restart[:-1] + b"!", want=len(restart)) == restart
        assert port.ask(request, want=len(answer)) == answer  # LF again after a restart
