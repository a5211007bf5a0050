"""Interop through `pyrtu gateway` onto a serial bus: pymodbus's and libmodbus's TCP
clients and pyrtu's, to a pyrtu slave and to a simulated drive on the other end of a
pseudo-terminal pair (socat; t35=0: a pty pair has no wire timing).  The gateway
runs as its own process (the command); 127.0.0.1 only.  An ASCII bus (--mode ascii)
at the end."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from peers import pattern
from peers.tools import (
    PeerBinaries,
    libmodbus_script,
    peer_env,
    pymodbus_server,
    pyrtu_slave_process,
)
from tcp_helpers import flood, stuck_socket

from pyrtu import ExceptionResponseError, encode_mbap, parse_tcp_stream, pdu
from pyrtu.tcp import AsyncTcpClient, TcpClient

pytest_plugins = ["peers.fixtures"]

TIMEOUT = 0.3  # the gateway's response timeout on the bus


@dataclass
class RunningGateway:
    proc: subprocess.Popen[str]
    host: str
    port: int
    rtu: str | None = None  # the RTU-over-TCP listener, HOST:PORT

    @property
    def url(self) -> str:
        return f"tcp://{self.host}:{self.port}"

    def stop(self) -> dict[str, Any]:
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=15)
        assert self.proc.returncode == 0, err
        stopped: dict[str, Any] = json.loads(out.splitlines()[-1])
        return stopped

    def kill(self) -> None:
        """After a test that failed before `stop`: no gateway left running."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def start_gateway(serial: str, *extra: str) -> RunningGateway:
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "gateway", "--listen", "127.0.0.1:0", "--port", serial,
         "--baudrate", "115200", "--parity", "N", "--t35", "0", "--timeout", str(TIMEOUT),
         "--json", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        proc.wait(10)
        raise AssertionError(
            f"the gateway did not start: {proc.stderr.read() if proc.stderr else ''}"
        )
    ready = json.loads(line)
    host, _, port = ready["listen"].rpartition(":")
    return RunningGateway(proc, host, int(port), ready.get("listen_rtu"))


@pytest.fixture
def pyrtu_bus(pty_pair: tuple[str, str]) -> Iterator[RunningGateway]:
    """A pyrtu slave at addresses 1 and 2 behind the gateway."""
    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0) as _slave:
        gw = start_gateway(f"{gw_side}=1-9")
        try:
            yield gw
        finally:
            gw.kill()


def test_pymodbus_tcp_client_through_the_gateway(pyrtu_bus: RunningGateway) -> None:
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(pyrtu_bus.host, port=pyrtu_bus.port, timeout=2, retries=0)
    assert client.connect()
    try:
        rr = client.read_holding_registers(10, count=8, device_id=1)
        assert not rr.isError() and rr.registers == pattern.holdings(1, 10, 8)
        rr = client.read_discrete_inputs(3, count=20, device_id=1)
        assert not rr.isError() and rr.bits[:20] == pattern.discretes(1, 3, 20)
        assert not client.write_registers(100, [5, 6, 7], device_id=1).isError()
        rr = client.read_holding_registers(100, count=3, device_id=1)
        assert rr.registers == [5, 6, 7]
        rr = client.read_holding_registers(60000, count=2, device_id=1)
        assert rr.isError() and rr.exception_code == 2  # the slave's own exception
        rr = client.read_holding_registers(0, count=1, device_id=9)
        assert rr.isError() and rr.exception_code == 0x0B  # nobody at 9 on the bus
        rr = client.read_holding_registers(0, count=1, device_id=20)
        assert rr.isError() and rr.exception_code == 0x0A  # no bus for unit 20
        # broadcast: no answer expected; the write reaches the slave
        client.write_register(200, 4242, device_id=0, no_response_expected=True)
        time.sleep(0.2)
        assert client.read_holding_registers(200, count=1, device_id=1).registers == [4242]
    finally:
        client.close()
    stats = pyrtu_bus.stop()
    assert stats["broadcasts"] == 1 and stats["timeouts"] == 1 and stats["no_route"] == 1


def test_libmodbus_tcp_client_through_the_gateway(
    pyrtu_bus: RunningGateway, peer_binaries: PeerBinaries
) -> None:
    device = f"tcp:{pyrtu_bus.host}:{pyrtu_bus.port}"
    ops = ["r03:0:10", "r01:5:30", "w16:300:1,2,3", "r03:300:3", "r04:7:4", "r03:60000:1",
           "slave:9", "r03:0:1", "slave:30", "r03:0:1"]  # fmt: skip
    results = libmodbus_script(peer_binaries, device, 1, ops, timeout_ms=2000)
    assert results[0]["values"] == pattern.holdings(1, 0, 10)
    assert results[1]["values"] == [int(b) for b in pattern.coils(1, 5, 30)]
    assert results[2]["ok"] and results[3]["values"] == [1, 2, 3]
    assert results[4]["values"] == pattern.inputs(1, 7, 4)
    assert [r.get("exception") for r in results[5:] if "exception" in r] == [2, 0x0B, 0x0A]


@pytest.mark.wall_clock
def test_dead_slave_answers_0x0b_in_time_and_others_go_on(pyrtu_bus: RunningGateway) -> None:
    async def main() -> None:
        dead = await AsyncTcpClient.connect(pyrtu_bus.url, timeout=10.0)
        live = await AsyncTcpClient.connect(pyrtu_bus.url, timeout=10.0)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        dead_task = asyncio.ensure_future(dead.request(7, pdu.read_request(3, 0, 1)))
        reads = [live.request(1, pdu.read_request(3, i, 2)) for i in range(20)]
        answers = await asyncio.gather(*reads)
        assert [pdu.parse_registers(a or b"", 2) for a in answers] == [
            pattern.holdings(1, i, 2) for i in range(20)
        ]
        with pytest.raises(ExceptionResponseError) as info:
            await dead_task
        elapsed = loop.time() - t0
        assert info.value.code == 0x0B
        # One bus timeout (0.3 s) plus 20 pty transactions of well under 10 ms each;
        # 10 x the timeout leaves room for a loaded 2-core machine, and is still far
        # below the clients' own 10 s timeout: the gateway answered, the client did not
        # time out.
        assert elapsed < 10 * TIMEOUT
        await dead.close()
        await live.close()

    asyncio.run(main())


def test_clients_leaving_mid_transaction_keep_the_bus_in_step(pyrtu_bus: RunningGateway) -> None:
    for i in range(20):  # send and leave at once: the answers arrive for nobody
        s = socket.create_connection((pyrtu_bus.host, pyrtu_bus.port))
        s.sendall(encode_mbap(i, 1, pdu.read_request(3, 500 + i, 1)))
        s.close()
    with TcpClient(pyrtu_bus.url, timeout=3.0) as c:
        for i in range(40):  # every answer is the right one: no stale frame in between
            got = c.request(1, pdu.read_request(3, i, 3))
            assert got is not None and pdu.parse_registers(got, 3) == pattern.holdings(1, i, 3)
    stats = pyrtu_bus.stop()
    assert stats["answers"] >= 40 and stats["timeouts"] == 0


def test_queue_overflow_through_the_gateway(pty_pair: tuple[str, str]) -> None:
    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0):
        gw = start_gateway(f"{gw_side}=1", "--max-queue", "2")
        try:
            s = socket.create_connection((gw.host, gw.port))
            s.sendall(b"".join(encode_mbap(n, 1, pdu.read_request(3, n, 1)) for n in range(10)))
            data = b""
            s.settimeout(5)
            while len(parse_tcp_stream(data, "master")) < 10 or data[-1:] == b"":
                chunk = s.recv(4096)
                assert chunk, "the gateway closed the connection"
                data += chunk
                if len(list(parse_tcp_stream(data, "master").frames())) == 10:
                    break
            s.close()
            answers = {f.transaction: f for f in parse_tcp_stream(data, "master").frames()}
            assert sorted(answers) == list(range(10))
            busy = [t for t, f in answers.items() if f.exception_code == 6]
            served = [t for t, f in answers.items() if f.exception_code is None]
            assert len(busy) >= 1 and len(served) >= 2  # two fit in the queue
            for t in served:
                assert pdu.parse_registers(answers[t].pdu, 1) == pattern.holdings(1, t, 1)
            stats = gw.stop()
            assert stats["busy"] == len(busy)
        finally:
            gw.kill()


def test_max_write_buffer_closes_a_stuck_client_and_others_go_on(pty_pair: tuple[str, str]) -> None:
    """--max-write-buffer: a client that sends and never reads is closed; a client
    reading its answers on the same bus is served before, during and after.  The
    limit is above asyncio's write high-water mark (64 KiB), where a gateway that
    stops reading a client instead of closing it would keep it forever."""
    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0):
        gw = start_gateway(f"{gw_side}=1", "--max-write-buffer", "131072")
        try:

            async def main() -> int:
                stuck = stuck_socket((gw.host, gw.port))
                big = pdu.read_request(3, 0, 125)
                burst = b"".join(encode_mbap(n, 1, big) for n in range(32))
                async with await AsyncTcpClient.connect(gw.url, timeout=5.0) as ok:
                    flooding = asyncio.ensure_future(flood(stuck, burst))
                    served = 0
                    while not flooding.done():
                        got = await ok.request(1, pdu.read_request(3, served % 100, 2))
                        assert pdu.parse_registers(got or b"", 2) == pattern.holdings(
                            1, served % 100, 2
                        )
                        served += 1
                    await flooding
                    stuck.close()
                    for i in range(10):
                        got = await ok.request(1, pdu.read_request(3, i, 1))
                        assert pdu.parse_registers(got or b"", 1) == pattern.holdings(1, i, 1)
                return served

            assert asyncio.run(main()) > 0
            stats = gw.stop()
            assert stats["slow_clients"] == 1 and stats["connections"] == 2
            assert stats["bad_headers"] == 0  # reset for what it left unread, not its framing
        finally:
            gw.kill()


def test_broadcast_is_sent_once_not_waited_for_nor_retried(pty_pair: tuple[str, str]) -> None:
    """With --retries 2 a broadcast still goes on the wire once (mbusd's issue #61: it
    waits for an answer to a broadcast and retries it); the gateway counts no timeout,
    answers nothing, and a read right after it is served."""
    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0) as slave:
        gw = start_gateway(f"{gw_side}=1-9", "--retries", "2")
        try:
            with socket.create_connection((gw.host, gw.port)) as s:
                s.settimeout(5)
                s.sendall(
                    encode_mbap(1, 0, pdu.write_register_request(210, 2100))
                    + encode_mbap(2, 0, pdu.write_registers_request(211, [2111, 2112]))
                    + encode_mbap(3, 1, pdu.read_request(3, 210, 3))
                )
                data = b""
                while len(data) < 6 or len(data) < 6 + int.from_bytes(data[4:6], "big"):
                    chunk = s.recv(4096)
                    assert chunk
                    data += chunk
                frames = list(parse_tcp_stream(data, "master").frames())
                # one answer, the read's: nothing for the broadcasts
                assert [f.transaction for f in frames] == [3]
                assert pdu.parse_registers(frames[0].pdu, 3) == [2100, 2111, 2112]
            stats = gw.stop()
            assert (stats["broadcasts"], stats["timeouts"], stats["answers"]) == (2, 0, 1)
        finally:
            gw.kill()
        counters = json.loads(slave.stop())
    assert (counters["broadcasts"], counters["requests"]) == (2, 1)  # no retry on the wire


@pytest.mark.wall_clock
def test_broadcast_delay_holds_the_bus_after_a_broadcast(pty_pair: tuple[str, str]) -> None:
    """--broadcast-delay: the silence the bus keeps after a broadcast (the devices'
    turnaround) before its next request, here 0.6 s.  (The serial master cuts it to
    the next request's --timeout, hence a timeout above it.)"""
    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0):
        gw = start_gateway(f"{gw_side}=1", "--broadcast-delay", "0.6", "--timeout", "2")
        try:
            with socket.create_connection((gw.host, gw.port)) as s:
                s.settimeout(10)
                t0 = time.monotonic()
                s.sendall(
                    encode_mbap(1, 0, pdu.write_register_request(220, 22))
                    + encode_mbap(2, 1, pdu.read_request(3, 220, 1))
                )
                data = b""
                while len(data) < 11:  # the read's answer: 7 + 4 bytes
                    chunk = s.recv(64)
                    assert chunk
                    data += chunk
                elapsed = time.monotonic() - t0
            frame = parse_tcp_stream(data, "master")[0]
            assert frame.transaction == 2 and pdu.parse_registers(frame.pdu, 1) == [22]
            # a lower bound: load can only lengthen it
            assert elapsed >= 0.6
            assert gw.stop()["broadcasts"] == 1
        finally:
            gw.kill()


@pytest.fixture
def drive_bus(pty_pair: tuple[str, str]) -> Iterator[RunningGateway]:
    """A simulated WEG CFW701 (address 1) behind the gateway."""
    gw_side, drive_side = pty_pair
    sim = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw701", "--port", drive_side,
         "--parity", "N", "--baudrate", "115200", "--t35", "0", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert sim.stdout is not None
    assert json.loads(sim.stdout.readline())["type"] == "ready"
    gw = start_gateway(f"{gw_side}=1")
    try:
        yield gw
    finally:
        for proc in (gw.proc, sim):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=15)


def test_simulated_drive_through_the_gateway(
    drive_bus: RunningGateway, peer_binaries: PeerBinaries
) -> None:
    with TcpClient(drive_bus.url, timeout=2.0) as c:
        got = c.request(1, pdu.device_id_request(1, 0))
        assert got is not None
        page = pdu.parse_device_id(got, 1)
        assert page.objects[0] == (0, b"WEG")
        status = c.request(1, pdu.read_request(3, 680, 1))
        assert status is not None and len(status) == 4
    device = f"tcp:{drive_bus.host}:{drive_bus.port}"
    # (libmodbus sizes no FC 43 answer, on TCP as on RTU: registers only here)
    results = libmodbus_script(
        peer_binaries, device, 1, ["r03:680:1", "w06:683:4096", "r03:683:1", "r03:9999:1"]
    )
    assert results[0]["ok"] and results[0]["values"] == pdu.parse_registers(status, 1)
    assert results[1]["ok"] and results[2]["values"] == [4096]  # P683 speed reference
    assert results[3]["exception"] == 2  # the manual's illegal data address
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(drive_bus.host, port=drive_bus.port, timeout=2, retries=0)
    assert client.connect()
    try:
        assert client.read_holding_registers(683, count=1, device_id=1).registers == [4096]
        assert not client.write_register(683, 2048, device_id=1).isError()
        assert client.read_holding_registers(683, count=1, device_id=1).registers == [2048]
        rr = client.read_holding_registers(9999, count=1, device_id=1)
        assert rr.isError() and rr.exception_code == 2
    finally:
        client.close()


def test_two_buses_behind_one_listener() -> None:
    from peers.tools import socat_pair

    with socat_pair() as (gw_a, dev_a), socat_pair() as (gw_b, dev_b):
        with pyrtu_slave_process(dev_a, 1, t35=0), pyrtu_slave_process(dev_b, 2, t35=0):
            gw = start_gateway(f"{gw_a}=1", "--port", f"{gw_b}=2-3", "--max-queue", "32")
            try:

                async def main() -> None:
                    c = await AsyncTcpClient.connect(gw.url, timeout=10.0, max_in_flight=64)
                    dead = asyncio.ensure_future(c.request(3, pdu.read_request(3, 0, 1)))
                    reads = [c.request(1 + i % 2, pdu.read_request(3, i, 2)) for i in range(40)]
                    answers = await asyncio.gather(*reads)
                    for i, a in enumerate(answers):  # each unit answered from its own bus
                        assert pdu.parse_registers(a or b"", 2) == pattern.holdings(1 + i % 2, i, 2)
                    with pytest.raises(ExceptionResponseError) as info:
                        await dead
                    assert info.value.code == 0x0B
                    await c.close()

                asyncio.run(main())
                stats = gw.stop()
                assert stats["bus_transactions"][0] == 20 and stats["bus_transactions"][1] == 21
            finally:
                gw.kill()


def test_rtu_over_tcp_clients_through_the_gateway(pty_pair: tuple[str, str]) -> None:
    from pyrtu import Master

    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0):
        gw = start_gateway(f"{gw_side}=1-5", "--listen-rtu", "127.0.0.1:0")
        try:
            assert gw.rtu is not None
            with Master(f"rtu+tcp://{gw.rtu}", timeout=2.0) as rtu, TcpClient(gw.url) as tcp:
                assert rtu.read_holding_registers(1, 30, 5) == pattern.holdings(1, 30, 5)
                rtu.write_register(1, 31, 3131)
                got = tcp.request(1, pdu.read_request(3, 31, 1))  # the same bus, both clients
                assert got is not None and pdu.parse_registers(got, 1) == [3131]
                with pytest.raises(ExceptionResponseError) as info:
                    rtu.read_holding_registers(4, 0, 1)  # nobody at 4 on the bus
                assert info.value.code == 0x0B
            stats = gw.stop()
            assert stats["connections"] == 2 and stats["timeouts"] == 1
        finally:
            gw.kill()


# -- an ASCII bus behind the gateway (--mode ascii) ----------------------------------


def test_ascii_bus_pymodbus_slave_through_the_gateway(pty_pair: tuple[str, str]) -> None:
    """`--mode ascii`: Modbus TCP clients (pyrtu's and pymodbus's) onto pymodbus's ASCII
    serial server; the gateway frames ':' ... LRC CR LF on the bus."""
    from pymodbus.client import ModbusTcpClient

    gw_side, slave_side = pty_pair
    with pymodbus_server(slave_side, 1, mode="ascii") as peer:
        gw = start_gateway(f"{gw_side}=1-9", "--mode", "ascii")
        try:
            with TcpClient(gw.url, timeout=3.0) as c:
                got = c.request(1, pdu.read_request(3, 5, 10))
                assert pdu.parse_registers(got or b"", 10) == pattern.holdings(1, 5, 10)
                got = c.request(1, pdu.read_request(2, 3, 20))
                assert pdu.parse_bits(got or b"", 20) == pattern.discretes(1, 3, 20)
                assert c.request(1, pdu.write_registers_request(120, [7, 8, 9])) is not None
                got = c.request(1, pdu.read_request(3, 120, 3))
                assert pdu.parse_registers(got or b"", 3) == [7, 8, 9]
                with pytest.raises(ExceptionResponseError) as info:
                    c.request(4, pdu.read_request(3, 0, 1))  # nobody at 4 on the bus
                assert info.value.code == 0x0B
                assert c.request(0, pdu.write_register_request(130, 1313)) is None  # broadcast
            client = ModbusTcpClient(gw.host, port=gw.port, timeout=3, retries=0)
            assert client.connect()
            try:
                rr = client.read_input_registers(2, count=6, device_id=1)
                assert not rr.isError() and rr.registers == pattern.inputs(1, 2, 6)
                assert client.read_holding_registers(130, count=1, device_id=1).registers == [
                    1313
                ]  # the broadcast reached the slave
                rr = client.read_holding_registers(60000, count=1, device_id=1)
                assert rr.isError() and rr.exception_code == 2  # the slave's own, in ASCII
            finally:
                client.close()
            stats = gw.stop()
            assert stats["broadcasts"] == 1 and stats["timeouts"] == 1
            assert stats["answers"] == 6 and stats["exceptions"] == 2
        finally:
            gw.kill()
    # the slave saw each request once (the broadcast too), none for unit 4, no stray answer
    assert peer.stats.split() == ["requests=8", "responses=7", "ignored=1", "stray=0"]


def test_ascii_bus_simulated_drive_through_the_gateway(
    pty_pair: tuple[str, str], peer_binaries: PeerBinaries
) -> None:
    """`--mode ascii` onto pyrtu's own ASCII slave (a simulated CV100, whose manual gives
    ASCII; address 5), with libmodbus's TCP client and an RTU-over-TCP client on the
    same bus."""
    from pyrtu import Master

    gw_side, drive_side = pty_pair
    sim = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", "cv100", "--port", drive_side,
         "--parity", "N", "--baudrate", "115200", "--mode", "ascii", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert sim.stdout is not None
    ready = json.loads(sim.stdout.readline())
    assert ready["type"] == "ready" and ready["format"].endswith("ASCII")
    gw = start_gateway(f"{gw_side}=1-9", "--mode", "ascii", "--listen-rtu", "127.0.0.1:0")
    try:
        device = f"tcp:{gw.host}:{gw.port}"
        # A1.01 = 0x0101 reads 5000 (the manual's RTU example); A0.06 = 0x0006 is the
        # acceleration time; 0x7777 is no function code's register
        results = libmodbus_script(
            peer_binaries, device, 5, ["r03:257:1", "w06:6:100", "r03:6:1", "r03:30583:1"]
        )
        assert results[0]["values"] == [5000]
        assert results[1]["ok"] and results[2]["values"] == [100]
        assert results[3]["exception"] == 2
        with Master(f"rtu+tcp://{gw.rtu}", timeout=3.0) as m:
            assert m.read_holding_registers(5, 6, 1) == [100]
            m.write_register(5, 6, 250)
            assert m.read_holding_registers(5, 6, 1) == [250]
            with pytest.raises(ExceptionResponseError) as info:
                m.read_holding_registers(7, 0, 1)  # nobody at 7 on the ASCII bus
            assert info.value.code == 0x0B
        stats = gw.stop()
        assert stats["answers"] == 6 and stats["exceptions"] == 2 and stats["timeouts"] == 1
    finally:
        for proc in (gw.proc, sim):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=15)


def test_unit_map_brings_tcp_units_0xff_and_0_to_a_serial_slave(
    pty_pair: tuple[str, str], peer_binaries: PeerBinaries
) -> None:
    """--unit-map 255=1,0=1: libmodbus's TCP client addressing unit 0, and pymodbus's
    addressing 0xFF (libmodbus's and many HMIs' default), reach serial slave 1 and
    get its answers; unit 0 mapped is answered, not broadcast."""
    from pymodbus.client import ModbusTcpClient

    gw_side, slave_side = pty_pair
    with pyrtu_slave_process(slave_side, 1, t35=0):
        gw = start_gateway(f"{gw_side}=1-9", "--unit-map", "255=1,0=1")
        try:
            device = f"tcp:{gw.host}:{gw.port}"
            ops = ["r03:0:5", "w06:30:77", "r03:30:1", "r04:60000:1"]
            r = libmodbus_script(peer_binaries, device, 0, ops, timeout_ms=2000)
            assert r[0]["values"] == pattern.holdings(1, 0, 5)
            assert r[1]["ok"] and r[2]["values"] == [77]
            assert r[3]["exception"] == 2  # the slave's own exception, through unit 0
            client = ModbusTcpClient(gw.host, port=gw.port, timeout=2, retries=0)
            assert client.connect()
            try:
                rr = client.read_holding_registers(30, count=1, device_id=255)
                assert not rr.isError() and rr.registers == [77]
                rr = client.read_input_registers(3, count=4, device_id=255)
                assert rr.registers == pattern.inputs(1, 3, 4)
            finally:
                client.close()
            stats = gw.stop()
        finally:
            gw.kill()
    assert stats["no_route"] == 0 and stats["broadcasts"] == 0 and stats["timeouts"] == 0
    assert stats["answers"] == 5 and stats["exceptions"] == 1
