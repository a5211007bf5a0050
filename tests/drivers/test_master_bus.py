"""The master where the bus misbehaves: retries, CRC errors, wrong and late answers,
stale input, echoing adapters, inter-frame timing, vendor function codes."""

from __future__ import annotations

import time
from collections.abc import Iterator
from types import ModuleType

import pytest
from ptylink import PtyLink, ScriptedSlave, make_store, serving
from waiting import ANSWER_TIMEOUT, SILENCE_TIMEOUT

from pyrtu import BONFIGLIOLI, CV100, add_crc, encode_ascii
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import (
    BusFault,
    ExceptionResponseError,
    FrameError,
    NoResponseError,
    SlaveException,
)


@pytest.fixture
def link() -> Iterator[PtyLink]:
    with PtyLink() as pty:
        yield pty


def regs_answer(slave: int, values: list[int]) -> bytes:
    body = bytes((slave, 3, 2 * len(values))) + b"".join(v.to_bytes(2, "big") for v in values)
    return add_crc(body)


def test_retries_after_no_response(link: PtyLink, backend: ModuleType) -> None:
    be = backend.BACKEND
    dropped = []

    def drop_first(data: bytes) -> bytes:
        if not dropped:
            dropped.append(data)
            return b""
        return data

    link.filters["a"] = drop_first
    with (
        serving(link.path_b, store=make_store(), t35=0, backend=be),
        Master(link.path_a, parity="N", t35=0, timeout=SILENCE_TIMEOUT, retries=2, backend=be) as m,
    ):
        assert m.read_holding_registers(1, 0, 2) == [1000, 1001]
        assert m.counters["retries"] == 1 and m.counters["timeouts"] == 1
        link.settle()
        request = bytes.fromhex("01 03 0000 0002") + add_crc(bytes.fromhex("01 03 0000 0002"))[-2:]
        assert link.wire("a") == request * 2
        m.retries = 0
        with pytest.raises(NoResponseError):
            m.read_holding_registers(9, 0, 1)


def test_exception_responses_are_not_retried(link: PtyLink) -> None:
    with (
        serving(link.path_b, store=make_store(), t35=0),
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT, retries=3) as m,
    ):
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(1, 500, 1)
        link.settle()
        assert len(link.wire("a")) == 8  # one request
        assert m.counters["retries"] == 0


@pytest.mark.parametrize("mode", ["rtu", "ascii"])
@pytest.mark.wall_clock
def test_corrupted_answer_is_a_frame_error(link: PtyLink, backend: ModuleType, mode: str) -> None:
    be = backend.BACKEND
    corrupt = {"on": True}

    def flip(data: bytes) -> bytes:
        if not corrupt["on"]:
            return data
        pos = len(data) // 2
        return (
            data[:pos] + bytes((data[pos] ^ (0x01 if mode == "rtu" else 0x02),)) + data[pos + 1 :]
        )

    link.filters["b"] = flip
    with (
        serving(link.path_b, store=make_store(), t35=0, backend=be, mode=mode),
        Master(link.path_a, parity="N", t35=0, timeout=1.0, backend=be, mode=mode) as m,
    ):
        start = time.monotonic()
        with pytest.raises(FrameError) as info:
            m.read_holding_registers(1, 0, 4)
        # A bad CRC fails the transaction at once, not after the timeout: half the timeout
        # (0.5 s) is ~100x a pty transaction, above a loaded 2-core VM's stalls (tens of ms).
        assert time.monotonic() - start < m.timeout / 2
        assert not isinstance(info.value, NoResponseError)
        assert "slave 1" in str(info.value) and "read_holding_registers" in str(info.value)
        c = m.counters
        assert c["crc_errors"] >= 1 and c["discarded_crc"] >= 1 and c["frame_errors"] == 1
        corrupt["on"] = False
        assert m.read_holding_registers(1, 0, 4) == [1000, 1001, 1002, 1003]


def test_retry_after_a_corrupted_answer(link: PtyLink) -> None:
    hits = []

    def flip_once(data: bytes) -> bytes:
        if hits:
            return data
        hits.append(1)
        return data[:3] + bytes((data[3] ^ 0x80,)) + data[4:]

    link.filters["b"] = flip_once
    with (
        serving(link.path_b, store=make_store(), t35=0),
        Master(link.path_a, parity="N", t35=0, timeout=0.5, retries=1) as m,
    ):
        assert m.read_holding_registers(1, 3, 3) == [1003, 1004, 1005]
        assert m.counters["retries"] == 1 and m.counters["crc_errors"] >= 1


@pytest.mark.wall_clock
def test_wrong_slave_and_wrong_function(link: PtyLink) -> None:
    def answer(request: bytes, n: int) -> list[tuple[float, bytes]]:
        if n == 0:
            return [(0, regs_answer(2, [5]))]  # another slave answers
        if n == 1:
            return [(0, add_crc(bytes.fromhex("01 04 02 0005")))]  # another function
        return [(0, regs_answer(1, [1, 2, 3]))]  # three registers for one

    with (
        ScriptedSlave(link.path_b, answer),
        Master(link.path_a, parity="N", t35=0, timeout=1.0) as m,
    ):
        for expected in ("from slave 2", "function 0x04", "PDU has 8 bytes, expected 4"):
            start = time.monotonic()
            with pytest.raises(FrameError, match=expected):
                m.read_holding_registers(1, 0, 1)
            # a short settling time, not the timeout: half of it (0.5 s) is ~100x a
            # pty transaction, above a loaded 2-core VM's stalls (tens of ms)
            assert time.monotonic() - start < m.timeout / 2
        assert m.counters["discarded_unexpected"] == 7 + 7 + 11


def test_late_answer_is_not_taken(link: PtyLink, backend: ModuleType) -> None:
    """The first request is answered after the master gave up; the next request
    (a different count) must get its own answer, not the late one."""

    def answer(request: bytes, n: int) -> list[tuple[float, bytes]]:
        count = request[5]
        values = [100 * (n + 1) + i for i in range(count)]
        return [(0.22 if n == 0 else 0.0, regs_answer(1, values))]

    with (
        ScriptedSlave(link.path_b, answer) as peer,
        Master(link.path_a, parity="N", t35=0, timeout=0.15, backend=backend.BACKEND) as m,
    ):
        with pytest.raises(NoResponseError):
            m.read_holding_registers(1, 0, 2)
        # sent while the late answer (2 registers) is still to come
        assert m.read_holding_registers(1, 0, 3) == [200, 201, 202]
        assert len(peer.requests) == 2
        assert m.counters["discarded_unexpected"] == 9  # the late answer, dropped
        assert m.counters["responses"] == 1


def test_late_answer_flushed_before_the_next_request(link: PtyLink) -> None:
    def answer(request: bytes, n: int) -> list[tuple[float, bytes]]:
        return [(0.25 if n == 0 else 0.0, regs_answer(1, [7 + n]))]

    with (
        ScriptedSlave(link.path_b, answer),
        Master(link.path_a, parity="N", t35=0, timeout=0.1) as m,
    ):
        with pytest.raises(NoResponseError):
            m.read_holding_registers(1, 0, 1)
        time.sleep(0.3)  # the late answer is in the input buffer now
        assert m.read_holding_registers(1, 0, 1) == [8]  # the same request: not the late [7]
        assert m.counters["discarded_stale"] == 7


def test_stale_input_flushed(link: PtyLink) -> None:
    with (
        serving(link.path_b, store=make_store(), t35=0),
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT) as m,
    ):
        link.inject("a", b"\x01\x03\x02\x00")  # half a frame left over from before
        time.sleep(0.05)
        assert m.read_holding_registers(1, 0, 1) == [1000]
        assert m.counters["discarded_stale"] == 4


def test_echoing_adapter_master(backend: ModuleType) -> None:
    be = backend.BACKEND
    with PtyLink(echo={"a"}) as link:
        with (
            serving(link.path_b, store=make_store(), t35=0, backend=be) as slave,
            Master(
                link.path_a, parity="N", t35=0, timeout=SILENCE_TIMEOUT, echo=True, backend=be
            ) as m,
        ):
            assert m.read_holding_registers(1, 0, 3) == [1000, 1001, 1002]
            m.write_register(1, 0, 5)
            m.write_register(0, 1, 6)  # a broadcast's echo is read back too
            assert m.read_holding_registers(1, 0, 2) == [5, 6]
            assert m.counters["echo_mismatches"] == 0
            # a collision: the echo differs from what was sent
            link.echo_filters["a"] = lambda data: data[:2] + b"\xff" + data[3:]
            with pytest.raises(BusFault, match="echo mismatch"):
                m.read_holding_registers(1, 0, 1)
            # an adapter that does not echo at all: the answer comes instead of the echo
            link.echo_filters["a"] = lambda data: b""
            with pytest.raises(BusFault, match="echo mismatch"):
                m.read_holding_registers(1, 0, 1)
            with pytest.raises(BusFault, match="did not come back"):
                m.read_holding_registers(9, 0, 1)  # and nothing at all
            assert m.counters["echo_mismatches"] == 3
            del link.echo_filters["a"]
            assert m.read_holding_registers(1, 1, 1) == [6]
            assert slave.counters["requests"] >= 4


def test_echoing_adapter_slave(backend: ModuleType) -> None:
    """An echoing slave must not take its own FC 06 answer (a copy of the request)
    for a request."""
    be = backend.BACKEND
    with PtyLink(echo={"b"}) as link:
        with (
            serving(link.path_b, store=make_store(), t35=0, echo=True, backend=be) as slave,
            Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT, backend=be) as m,
        ):
            for i in range(5):
                m.write_register(1, 10, i)
                assert m.read_holding_registers(1, 10, 1) == [i]
            link.settle(0.05)
            assert slave.counters["responses"] == 10
            assert slave.counters["echo_dropped"] == 10
            assert slave.counters["requests"] == 10
            # each request got exactly one answer: 5 x (8 + 7) bytes
            assert len(link.wire("b")) == 5 * (8 + 7)


def test_inter_frame_silence(link: PtyLink, backend: ModuleType) -> None:
    """With the spec's timing (9600 baud 8N1: t3.5 = 3.646 ms), a request never
    follows the previous answer sooner than t3.5."""
    be = backend.BACKEND
    with (
        serving(link.path_b, store=make_store(), baudrate=9600, t35=0, backend=be),
        Master(link.path_a, 9600, parity="N", timeout=0.5, backend=be) as m,
    ):
        assert m.t35 == pytest.approx(3.5 * 10 / 9600, abs=1e-6)
        for _ in range(6):
            m.read_holding_registers(1, 0, 1)
        gaps = link.gaps("b", "a")
        assert len(gaps) == 5
        # A causal lower bound, not a wall_clock one: the master hears the answer only
        # after the link thread stamped it, and the request is stamped after the
        # master sent it, so a slow machine only widens the gaps seen.
        assert min(gaps) >= m.t35 * 0.95


def test_slave_answers_after_t35_and_response_delay(link: PtyLink) -> None:
    with (
        serving(link.path_b, store=make_store(), baudrate=9600, response_delay=0.02) as slave,
        Master(link.path_a, 9600, parity="N", t35=0, timeout=0.5) as m,
    ):
        for _ in range(4):
            m.read_holding_registers(1, 0, 1)
        gaps = link.gaps("a", "b")
        assert len(gaps) == 4
        # causal too (see above): the slave hears the request after the link stamped it
        assert min(gaps) >= slave.t35 + 0.02 - 0.0001, gaps  # 0.1 ms: a tenth of a character


@pytest.mark.parametrize("mode", ["rtu", "ascii"])
@pytest.mark.wall_clock
def test_vendor_function_codes(link: PtyLink, backend: ModuleType, mode: str) -> None:
    """Bonfiglioli FC 100/101 (32-bit parameters) and CV100 0x41, with length rules:
    answers are framed by their length, not by a timeout."""
    be = backend.BACKEND
    params = {0x01E1: 1000}

    def read32(slave: Slave, unit: int, pdu: bytes) -> bytes:
        number = int.from_bytes(pdu[1:3], "big")
        if number not in params:
            raise SlaveException(4)
        return pdu[:1] + params[number].to_bytes(4, "big")

    def write32(slave: Slave, unit: int, pdu: bytes) -> bytes:
        params[int.from_bytes(pdu[1:3], "big")] = int.from_bytes(pdu[3:7], "big")
        return pdu

    def keep(slave: Slave, unit: int, pdu: bytes) -> bytes:
        slave.store_for(unit).holding_registers.write(
            int.from_bytes(pdu[1:3], "big"), [int.from_bytes(pdu[3:5], "big")]
        )
        return pdu

    with serving(link.path_b, store=make_store(), t35=0, backend=be, mode=mode) as slave:
        slave.register_function(100, read32, *BONFIGLIOLI[100])
        slave.register_function(101, write32, *BONFIGLIOLI[101])
        slave.register_function(0x41, keep, *CV100[0x41], broadcast=True)
        with Master(link.path_a, parity="N", t35=0, timeout=1.0, backend=be, mode=mode) as m:
            req, resp = BONFIGLIOLI[100]
            start = time.monotonic()
            assert m.execute(
                1, 100, bytes.fromhex("01E1"), request_rule=req, response_rule=resp
            ) == bytes.fromhex("000003E8")
            # Framed by the length rule as soon as the last byte came, not by waiting
            # for the rest of an unknown length up to the timeout: a fifth of it
            # (0.2 s) is ~40x a pty transaction, above a loaded 2-core VM's stalls.
            assert time.monotonic() - start < m.timeout / 5
            m.add_rule(101, *BONFIGLIOLI[101])
            assert m.execute(1, 101, bytes.fromhex("2177 000003E8")) == bytes.fromhex(
                "2177 000003E8"
            )
            assert params[0x2177] == 1000
            with pytest.raises(ExceptionResponseError) as info:
                m.execute(1, 100, bytes.fromhex("2640"))  # unknown parameter 1600 (manual 8.1.3)
            assert (info.value.function, info.value.code) == (100, 4)
            m.execute(0, 0x41, bytes.fromhex("0005 0063"))  # broadcast vendor write
            time.sleep(0.05)
            assert slave.store_for(1).holding_registers.get(5) == 0x63
            assert m.execute(
                1, 0x41, bytes.fromhex("0006 0064"), response_rule=CV100[0x41][1]
            ) == bytes.fromhex("0006 0064")


def test_ascii_frames_on_the_wire(link: PtyLink) -> None:
    with (
        serving(link.path_b, store=make_store(), mode="ascii"),
        Master(link.path_a, parity="N", timeout=0.5, mode="ascii") as m,
    ):
        assert m.read_holding_registers(1, 0, 1) == [1000]
        link.settle()
        assert link.wire("a") == encode_ascii(bytes.fromhex("01 03 0000 0001"))
        assert link.wire("b") == encode_ascii(bytes.fromhex("01 03 02 03E8"))
