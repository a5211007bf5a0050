"""The Modbus TCP client: the sans-I/O protocol with synthetic time, and the blocking
and asyncio drivers against real servers (pymodbus and libmodbus, on 127.0.0.1)."""

from __future__ import annotations

import asyncio
import socket
import threading
from collections.abc import Iterator

import pytest
from peers import pattern
from peers.tools import free_tcp_port

from pyrtu import (
    ExceptionResponseError,
    FrameError,
    NoResponseError,
    PortError,
    encode_mbap,
    pdu,
)
from pyrtu.tcp import AsyncTcpClient, TcpClient, parse_tcp_url
from pyrtu.tcp.protocol import TcpClientProtocol

pytest_plugins = ["peers.fixtures"]

READ = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 2)


def answer(tid: int, unit: int, body: str) -> bytes:
    return encode_mbap(tid, unit, bytes.fromhex(body))


# -- the sans-I/O protocol ---------------------------------------------------------


def test_answers_in_any_order_are_matched_by_transaction_id() -> None:
    p = TcpClientProtocol(timeout=1.0, max_in_flight=4)
    sent = [p.send_request(unit, READ, 0.0) for unit in (1, 2, 3)]
    tids = [t for t, _ in sent]
    assert len(set(tids)) == 3 and all(data[7:] == READ for _, data in sent)
    assert p.in_flight == 3 and p.deadline() == 1.0
    stream = answer(tids[2], 3, "0304000a000b") + answer(tids[0], 1, "030400010002")
    for i in range(len(stream)):  # one byte per read
        p.receive_data(stream[i : i + 1], 0.1)
    assert p.next_result() == (tids[2], bytes.fromhex("0304000a000b"))
    assert p.next_result() == (tids[0], bytes.fromhex("030400010002"))
    assert p.next_result() is None and p.in_flight == 1
    p.receive_data(answer(tids[1], 2, "8302"), 0.2)
    tid, err = p.next_result()  # type: ignore[misc]
    assert tid == tids[1] and isinstance(err, ExceptionResponseError)
    assert (err.slave, err.function, err.code) == (2, 3, 2)
    assert p.counters["responses"] == 2 and p.counters["exceptions"] == 1


def test_answer_end_is_the_time_of_the_latest_answer() -> None:
    p = TcpClientProtocol(timeout=0.5, max_in_flight=4)
    assert p.answer_end is None
    t1, _ = p.send_request(1, READ, 10.0)
    t2, _ = p.send_request(1, READ, 10.0)
    p.receive_data(answer(t1, 1, "030400010002")[:5], 10.1)  # a partial answer: no answer yet
    assert p.answer_end is None
    p.receive_data(answer(t1, 1, "030400010002")[5:], 10.2)
    assert p.answer_end == 10.2
    p.handle_timer(10.6)  # t2 times out: no answer, the stamp stays
    p.receive_data(answer(t2, 1, "030400010002"), 10.7)  # late, dropped: not an answer
    assert p.answer_end == 10.2 and p.counters["late"] == 1
    t3, _ = p.send_request(1, READ, 11.0)
    p.receive_data(answer(t3, 1, "8302"), 11.3)  # an exception answer is an answer
    assert p.answer_end == 11.3


def test_timeout_then_late_answer_is_dropped() -> None:
    p = TcpClientProtocol(timeout=0.5)
    tid, _ = p.send_request(7, READ, 10.0)
    p.handle_timer(10.4)
    assert p.next_result() is None
    p.handle_timer(10.5)
    t, err = p.next_result()  # type: ignore[misc]
    assert t == tid and isinstance(err, NoResponseError) and isinstance(err, TimeoutError)
    assert p.deadline() is None
    p.receive_data(answer(tid, 7, "030400010002"), 11.0)
    assert p.next_result() is None and p.counters["late"] == 1


def test_wrong_unit_or_function_is_a_frame_error() -> None:
    p = TcpClientProtocol()
    t1, _ = p.send_request(1, READ, 0.0)
    t2, _ = p.send_request(2, READ, 0.0)
    p.receive_data(answer(t1, 9, "030400010002") + answer(t2, 2, "0402000a"), 0.1)
    for expected in (t1, t2):
        t, err = p.next_result()  # type: ignore[misc]
        assert t == expected and isinstance(err, FrameError) and isinstance(err, ValueError)
    assert p.counters["frame_errors"] == 2


def test_bad_header_breaks_the_connection() -> None:
    p = TcpClientProtocol()
    t1, _ = p.send_request(1, READ, 0.0)
    t2, _ = p.send_request(1, READ, 0.0)
    p.receive_data(bytes.fromhex("0001 0007 0003 01 8302"), 0.1)  # protocol id 7
    results = [p.next_result(), p.next_result()]
    assert [r[0] for r in results if r] == [t1, t2]
    assert all(isinstance(r[1], FrameError) for r in results if r)
    assert p.broken is not None
    with pytest.raises(PortError, match="unusable"):
        p.send_request(1, READ, 0.2)


def test_broadcast_completes_at_once_and_limits_hold() -> None:
    p = TcpClientProtocol(max_in_flight=2)
    tid, data = p.send_request(0, pdu.write_register_request(1, 5), 0.0)
    assert p.next_result() == (tid, None) and p.in_flight == 0 and data[6] == 0
    assert p.counters["broadcasts"] == 1
    p.send_request(1, READ, 0.0)
    p.send_request(1, READ, 0.0)
    with pytest.raises(RuntimeError, match="in flight"):
        p.send_request(1, READ, 0.0)
    with pytest.raises(ValueError, match="unit"):
        p.send_request(256, READ, 0.0)
    with pytest.raises(ValueError, match="timeout"):
        TcpClientProtocol(timeout=0)
    with pytest.raises(ValueError, match="max_in_flight"):
        TcpClientProtocol(max_in_flight=0)


def test_transaction_ids_wrap_and_skip_those_in_flight() -> None:
    p = TcpClientProtocol(max_in_flight=3)
    p._tid = 0xFFFE
    a, _ = p.send_request(1, READ, 0.0)
    b, _ = p.send_request(1, READ, 0.0)
    assert (a, b) == (0xFFFF, 0)
    p.cancel(a)
    c, _ = p.send_request(1, READ, 0.0)
    assert c == 1


def test_server_close_fails_what_is_in_flight() -> None:
    p = TcpClientProtocol(where="tcp://x:1")
    tid, _ = p.send_request(1, READ, 0.0)
    p.receive_data(answer(tid, 1, "030400010002")[:5], 0.1)
    p.receive_data(b"", 0.2)
    t, err = p.next_result()  # type: ignore[misc]
    assert t == tid and isinstance(err, PortError) and "tcp://x:1" in str(err)


def test_urls() -> None:
    assert parse_tcp_url("tcp://127.0.0.1:5020") == ("127.0.0.1", 5020)
    assert parse_tcp_url("tcp://plc") == ("plc", 502)
    assert parse_tcp_url("tcp://[::1]:15") == ("::1", 15)
    for bad in ("quic://h:1", "tcp://:5", "tcp://h:99999", "tcp://h:1/x", "h:1"):
        with pytest.raises(ValueError, match="tcp://"):
            parse_tcp_url(bad)


# -- the drivers against real servers ------------------------------------------------


def test_sync_client_against_real_servers(tcp_server: tuple[str, int]) -> None:
    with TcpClient(tcp_server[0], timeout=2.0) as c:
        got = c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 10, 5))
        assert got is not None
        assert pdu.parse_registers(got, 5) == pattern.holdings(1, 10, 5)
        c.request(1, pdu.write_registers_request(20, [7, 8, 9]))
        got = c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 20, 3))
        assert got is not None and pdu.parse_registers(got, 3) == [7, 8, 9]
        got = c.request(1, pdu.read_request(pdu.READ_COILS, 0, 20))
        assert got is not None and pdu.parse_bits(got, 20) == pattern.coils(1, 0, 20)
        with pytest.raises(ExceptionResponseError) as info:
            c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 60000, 10))
        assert info.value.code == 2
        assert c.counters["responses"] == 4 and c.counters["exceptions"] == 1


def test_async_client_pipelines_against_real_servers(tcp_server: tuple[str, int]) -> None:
    url, window = tcp_server

    async def main() -> None:
        async with await AsyncTcpClient.connect(url, timeout=2.0, max_in_flight=window) as c:
            answers = await asyncio.gather(
                *(c.request(1, pdu.read_request(pdu.READ_INPUT_REGISTERS, i, 4)) for i in range(50))
            )
            for i, got in enumerate(answers):
                assert got is not None and pdu.parse_registers(got, 4) == pattern.inputs(1, i, 4)
            with pytest.raises(ExceptionResponseError):
                await c.request(1, pdu.read_request(pdu.READ_INPUT_REGISTERS, 60000, 1))
            assert c.counters["responses"] == 50

    asyncio.run(main())


def test_connection_refused_is_a_port_error() -> None:
    port = free_tcp_port()
    with pytest.raises(PortError, match=f"127.0.0.1:{port}"):
        TcpClient(f"tcp://127.0.0.1:{port}", timeout=1.0)

    async def main() -> None:
        with pytest.raises(PortError, match="cannot connect"):
            await AsyncTcpClient.connect(f"tcp://127.0.0.1:{port}")

    asyncio.run(main())


@pytest.fixture
def silent_server() -> Iterator[tuple[int, list[socket.socket]]]:
    """A TCP server that accepts, reads and never answers (closes on request)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)
    accepted: list[socket.socket] = []

    def run() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            accepted.append(conn)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    yield listener.getsockname()[1], accepted
    listener.close()
    for c in accepted:
        c.close()


def test_no_answer_times_out_and_close_fails_the_request(
    silent_server: tuple[int, list[socket.socket]],
) -> None:
    port, accepted = silent_server
    with TcpClient(f"tcp://127.0.0.1:{port}", timeout=0.2) as c:
        with pytest.raises(NoResponseError):
            c.request(1, READ)
        assert c.counters["timeouts"] == 1

    async def main() -> None:
        c = await AsyncTcpClient.connect(f"tcp://127.0.0.1:{port}", timeout=5.0)
        task = asyncio.ensure_future(c.request(1, READ))
        await asyncio.sleep(0.1)
        for conn in accepted:
            conn.close()  # the server goes away mid-transaction
        with pytest.raises(PortError):
            await asyncio.wait_for(task, 2.0)
        with pytest.raises(PortError):
            await c.request(1, READ)
        await c.close()

    asyncio.run(main())
