"""The command line on network ports, against real peers on loopback: ``pyrtu scan``
through a pyrtu gateway in front of a virtual RS-485 bus, against pyrtu's TcpServer
(which honours the unit id) and against libmodbus's TCP server (which answers every
unit id); a connect timeout's message; ``-vv`` frames on ``tcp://`` and
``rtu+tcp://``; a URL scheme nobody opens; the busy message of the poller."""

from __future__ import annotations

import asyncio
import re
import signal
import socket
import struct
import threading
import time
from collections.abc import Coroutine, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import pytest
from cli_helpers import Background, pyrtu
from peers import pattern
from vectors import crc_bitwise

import pyrtu as pyrtu_api
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.port import open_port
from pyrtu.drivers.slave import Slave
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.gateway import Gateway
from pyrtu.pdu.errors import ExceptionResponseError, PortBusyError, PortError
from pyrtu.protocol.datastore import DataStore
from pyrtu.tcp import AsyncTcpClient, TcpClient
from pyrtu.tcp.server import TcpServer
from pyrtu.vbus import VirtualBus

pytest_plugins = ["peers.fixtures"]

BAUD = 38400
REAL = 4  # the one slave on the bus behind the gateway
CARRIED = range(1, 7)  # the unit ids the gateway routes to the bus (7 and up: 0x0A)
GATEWAY_TIMEOUT = 0.5  # the gateway's bus timeout (0x0B after it): above scan's old 0.1 s
VALUE = 0x1234  # holding register 0 of the real slave
T = TypeVar("T")


class LoopThread:
    """An asyncio loop in a thread of its own, for the servers the CLI talks to."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(30)
        self.loop.close()


@dataclass
class Peers:
    url: str  # tcp:// of the gateway
    rtu_url: str  # rtu+tcp:// of the gateway
    unit_server: str  # tcp:// of a TcpServer serving unit 7 only


@pytest.fixture(scope="module")
def peers() -> Iterator[Peers]:
    """A virtual bus with one slave (address REAL) on drop 1; the gateway's master on
    drop 0 (bus timeout GATEWAY_TIMEOUT) carrying units CARRIED over TCP and RTU over
    TCP; and a TcpServer for unit 7 (any other unit id: 0x0A)."""
    store = DataStore()
    store.holding_registers.add_range(0, [VALUE] * 10)
    unit_store = DataStore()
    unit_store.holding_registers.add_range(0, [7] * 10)
    loop = LoopThread()
    with (
        VirtualBus(2, baudrate=BAUD, parity="N") as vbus,
        Slave(vbus.paths[1], REAL, store, baudrate=BAUD, parity="N") as slave,
    ):
        slave.start()

        async def start() -> tuple[AsyncMaster, Gateway, TcpServer]:
            master = AsyncMaster(vbus.paths[0], BAUD, "N", timeout=GATEWAY_TIMEOUT)
            gw = Gateway([(master, CARRIED)])
            await gw.start("127.0.0.1", 0, rtu=("127.0.0.1", 0))
            server = TcpServer(SlaveBase(7, unit_store, line=LineConfig()))
            await server.start("127.0.0.1", 0)
            return master, gw, server

        master, gw, server = loop.run(start())
        assert gw.address and gw.rtu_address and server.address
        try:
            yield Peers(
                f"tcp://127.0.0.1:{gw.address[1]}",
                f"rtu+tcp://127.0.0.1:{gw.rtu_address[1]}",
                f"tcp://127.0.0.1:{server.address[1]}",
            )
        finally:

            async def stop() -> None:
                await server.close()
                await gw.close()
                await master.close()

            loop.run(stop())
            loop.stop()


# -- the shared classification ---------------------------------------------------------------


def test_no_device_answered_is_a_gateway_exception() -> None:
    """Application Protocol V1.1b section 7: 0x0A gateway path unavailable, 0x0B gateway
    target device failed to respond; every other exception is the device's answer."""
    assert ExceptionResponseError(3, 3, 0x0A).no_device_answered
    assert ExceptionResponseError(3, 3, 0x0B).no_device_answered
    for code in (1, 2, 3, 4, 5, 6, 8, 9, 12):
        assert not ExceptionResponseError(3, 3, code).no_device_answered, code


# -- scan --------------------------------------------------------------------------------------


def test_scan_through_a_gateway_finds_the_slave_behind_silent_addresses(peers: Peers) -> None:
    """Units 1-3, 5, 6: the gateway answers 0x0B after its 0.5 s bus timeout (no slave);
    7, 8: 0x0A (no bus): none of them is a slave.  Slave 4 comes after three silent
    addresses, whose probes the gateway serves one after the other: the default
    timeout on tcp:// waits for the gateway (the old 0.1 s gave up, and slave 4's
    probe timed out queued behind them)."""
    r = pyrtu("scan", peers.url, "--range", "1-8", "--json")
    assert r.code == 0, r.err
    doc = r.json()
    assert doc["slaves"] == [REAL], doc
    assert doc["found"][0]["detail"] == f"holding register 0 = {VALUE} (0x{VALUE:04X})"
    assert "late_answers" not in doc and "every_unit" not in doc


def test_scan_header_shows_the_tcp_endpoint_not_a_serial_format(peers: Peers) -> None:
    r = pyrtu("scan", peers.url, "--range", f"{REAL}-{REAL}")
    assert r.code == 0, r.err
    lines = r.out.splitlines()
    assert lines[0] == (
        f"scanning slaves {REAL}-{REAL} on {peers.url} (Modbus TCP, timeout 1000 ms, probe FC 3)"
    )
    assert "baud" not in r.out
    assert lines[-1].startswith(f"1 slave found ({REAL}) in ")


def test_scan_over_rtu_over_tcp_waits_for_the_gateway_too(peers: Peers) -> None:
    """RTU over TCP to the same gateway: it keeps silent for a silent address (as a
    serial line) after its 0.5 s bus timeout, and the next probes wait behind it."""
    r = pyrtu("scan", peers.rtu_url, "--range", "2-4")
    assert r.code == 0, r.err
    assert r.out.splitlines()[0] == (
        f"scanning slaves 2-4 on {peers.rtu_url} (RTU over TCP, timeout 1000 ms, probe FC 3)"
    )
    assert f"1 slave found ({REAL})" in r.out


def test_scan_reports_answers_that_came_after_its_timeout(peers: Peers) -> None:
    """A --timeout below the gateway's bus timeout: the 0x0B answers come after it
    (the first at 0.5 s, while the third probe waits); the scan says that slaves may
    have been missed instead of keeping silent."""
    r = pyrtu("scan", peers.url, "--range", "1-6", "--timeout", "0.2", "--json")
    assert r.code in (0, 4), r.err
    assert r.json()["late_answers"] >= 1, r.out
    assert "slaves may have been missed; raise --timeout" in r.err


def test_scan_of_a_server_that_honours_the_unit_id(peers: Peers) -> None:
    """pyrtu's TcpServer serves unit 7 and answers 0x0A to any other unit id."""
    r = pyrtu("scan", peers.unit_server, "--range", "1-10", "--json")
    assert r.code == 0, r.err
    assert r.json()["slaves"] == [7]


def test_scan_of_a_device_that_answers_every_unit_id(libmodbus_tcp: str) -> None:
    """libmodbus's TCP server ignores the unit id (its TCP backend filters none): the
    scan says so instead of listing 247 slaves."""
    holding = pattern.holdings(1, 0, 1)[0]
    r = pyrtu("scan", libmodbus_tcp, "--range", "1-247", "--json")
    assert r.code == 0, r.err
    doc = r.json()
    assert doc["every_unit"] is True and doc["slaves"] == [] and doc["found"] == [], doc
    assert doc["device"]["detail"] == f"holding register 0 = {holding} (0x{holding:04X})"
    text = pyrtu("scan", libmodbus_tcp, "--range", "1-247")
    assert text.code == 0, text.err
    lines = text.out.splitlines()
    assert lines[1] == (
        "the device answers every unit id: unit 248, which no slave can have, answered "
        f"holding register 0 = {holding} (0x{holding:04X})"
    ), text.out
    assert len(lines) == 3 and lines[2].startswith("one Modbus TCP device"), text.out


# -- connect timeouts --------------------------------------------------------------------------


@pytest.fixture
def full_listener() -> Iterator[tuple[str, int]]:
    """A loopback listener whose accept queue is full (backlog 0, never accepting):
    Linux drops the SYNs of further connects, which then time out."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    address = listener.getsockname()
    fillers: list[socket.socket] = []
    try:
        for _ in range(8):
            try:
                fillers.append(socket.create_connection(address, timeout=0.2))
            except TimeoutError:
                break
        else:
            pytest.fail("the listener's queue never filled")
        yield address
    finally:
        for s in fillers:
            s.close()
        listener.close()


def test_a_connect_timeout_says_how_long_it_waited(full_listener: tuple[str, int]) -> None:
    host, port = full_listener
    url = f"tcp://{host}:{port}"
    with pytest.raises(PortError) as sync:
        TcpClient(url, timeout=0.2)
    assert str(sync.value) == f"{url}: cannot connect: timed out after 0.2 s"

    async def connect() -> None:
        await AsyncTcpClient.connect(url, timeout=0.25)

    with pytest.raises(PortError) as aio:
        asyncio.run(connect())
    assert str(aio.value) == f"{url}: cannot connect: timed out after 0.25 s"


def test_a_refused_connect_reads_the_same_from_every_client() -> None:
    """The blocking client, the asyncio one (asyncio words it "Connect call failed")
    and RTU over TCP: what the OS said (errno ECONNREFUSED's text)."""
    import errno
    import os

    with socket.socket() as s:  # a loopback port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    refused = os.strerror(errno.ECONNREFUSED)
    url = f"tcp://127.0.0.1:{port}"
    with pytest.raises(PortError) as sync:
        TcpClient(url, timeout=1.0)
    assert str(sync.value) == f"{url}: cannot connect: {refused}"
    with pytest.raises(PortError) as aio:
        asyncio.run(AsyncTcpClient.connect(url, timeout=1.0))
    assert str(aio.value) == f"{url}: cannot connect: {refused}"
    rtu = f"rtu+tcp://127.0.0.1:{port}"
    with pytest.raises(PortError) as serial_link:
        pyrtu_api.Master(rtu)
    assert str(serial_link.value) == f"{rtu}: cannot connect: {refused}"


def test_a_connect_timeout_of_rtu_over_tcp(full_listener: tuple[str, int]) -> None:
    """pyserial's socket:// connects with its own 5 s timeout (POLL_TIMEOUT)."""
    from serial.urlhandler.protocol_socket import POLL_TIMEOUT

    url = f"rtu+tcp://{full_listener[0]}:{full_listener[1]}"
    with pytest.raises(PortError) as info:
        pyrtu_api.Master(url)
    assert str(info.value) == f"{url}: cannot connect: timed out after {POLL_TIMEOUT:g} s"


def test_the_cli_says_a_connect_timed_out(full_listener: tuple[str, int], tmp_path: Path) -> None:
    """``pyrtu read`` (the blocking client) and ``pyrtu poll --config`` (the asyncio one)."""
    host, port = full_listener
    url = f"tcp://{host}:{port}"
    r = pyrtu("read", url, "0", "--timeout", "0.3")
    assert r.code == 3
    assert r.err.strip() == f"pyrtu read: port error: {url}: cannot connect: timed out after 0.3 s"
    config = tmp_path / "points.toml"
    config.write_text(
        f'[[bus]]\nname = "plc"\nport = "{url}"\ntimeout = 0.3\n\n'
        '[[point]]\nname = "x"\nbus = "plc"\nslave = 1\ntable = "holding"\naddress = 0\n'
    )
    r = pyrtu("poll", "--config", config, "--duration", "1", "--json")
    assert r.code == 3, r.err
    events = [d for d in r.json_lines() if d.get("event") == "port"]
    assert events and events[0]["error"] == "cannot connect: timed out after 0.3 s", r.out


# -- -vv frames -------------------------------------------------------------------------------


def test_vv_logs_the_mbap_frames_on_tcp(peers: Peers) -> None:
    """The request and the answer, whole (Messaging on TCP/IP Implementation Guide
    3.1.3: transaction id, protocol id 0, length, unit id, then the PDU)."""
    r = pyrtu("-vv", "read", peers.unit_server, "--slave", "7", "0", "2")
    assert r.code == 0, r.err
    sent = struct.pack(">HHHBBHH", 1, 0, 6, 7, 3, 0, 2).hex(" ")
    answer = struct.pack(">HHHBBBHH", 1, 0, 7, 7, 3, 4, 7, 7).hex(" ")
    assert f"TX unit 7 fc 3 tid 1: {sent}" in r.err, r.err
    assert f"RX unit 7 fc 3 tid 1: {answer} (" in r.err, r.err
    quiet = pyrtu("-v", "read", peers.unit_server, "--slave", "7", "0", "2")
    assert "TX unit" not in quiet.err and "RX unit" not in quiet.err


def test_vv_logs_the_rtu_frames_on_rtu_over_tcp(peers: Peers) -> None:
    r = pyrtu("-vv", "read", peers.rtu_url, "--slave", REAL, "0", "1")
    assert r.code == 0, r.err
    request = struct.pack(">BBHH", REAL, 3, 0, 1)
    crc = struct.pack("<H", crc_bitwise(request)).hex(" ")
    assert f"TX slave {REAL} fc 3: {request.hex(' ')} {crc}" in r.err, r.err
    assert f"RX slave {REAL} fc 3: {struct.pack('>BBBH', REAL, 3, 2, VALUE).hex(' ')}" in r.err


def test_vv_logs_the_frames_a_tcp_server_receives_and_sends() -> None:
    """``pyrtu -vv simulate --tcp``: the server side (the gateway's machinery, which
    TcpServer and the gateway share) logs each request and answer, whole."""
    sim = Background(
        "-vv", "simulate", "cfw100", "--tcp", "127.0.0.1:0", "--address", "1", "--duration", "30"
    )
    try:
        port = _wait_for(sim, r"Modbus TCP on 127\.0\.0\.1:(\d+)")
        r = pyrtu("read", f"tcp://127.0.0.1:{port}", "0", "--json")
        assert r.code == 0, r.err
        value = r.json()["values"][0]
        _wait_for(sim, r"TX unit 1: ")
    finally:
        sim.proc.send_signal(signal.SIGTERM)
        done = sim.finish()
    request = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 1).hex(" ")
    answer = struct.pack(">HHHBBBH", 1, 0, 5, 1, 3, 2, value).hex(" ")
    assert f"connection 1: RX unit 1: {request}" in done.err, done.err
    assert f"connection 1: TX unit 1: {answer}" in done.err, done.err


def _wait_for(proc: Background, pattern: str, timeout: float = 20.0) -> str:
    """The first group of ``pattern`` in what ``proc`` printed on stderr (waits)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = re.search(pattern, "".join(proc.err))
        if found:
            return found.group(1) if found.re.groups else found.group(0)
        time.sleep(0.05)
    raise AssertionError(f"{pattern!r} not in {''.join(proc.err)!r}")


# -- URL schemes -------------------------------------------------------------------------------


def test_a_scheme_nobody_opens_is_a_usage_error_naming_the_supported_ones(
    tmp_path: Path,
) -> None:
    for argv in (
        ("read", "quic://127.0.0.1:502", "0"),
        ("scan", "quic://127.0.0.1:502"),
        ("gateway", "--listen", "127.0.0.1:0", "--port", "quic://127.0.0.1:502=1"),
    ):
        r = pyrtu(*argv)
        assert r.code == 2, (argv, r.err)
        assert (
            "quic://127.0.0.1:502: unsupported scheme quic://; supported: tcp://, rtu+tcp://"
            in (r.err)
        )
        # pyserial's URL handlers (pyserial's documentation, "URL Handlers")
        assert all(s in r.err for s in ("socket://", "rfc2217://", "loop://")), r.err
        assert "refused" not in r.err and "Traceback" not in r.err
    sniff = pyrtu("sniff", "quic://127.0.0.1:502", "--duration", "1")
    assert sniff.code == 2 and "unsupported scheme quic://; supported: " in sniff.err
    assert "tcp://" not in sniff.err.split("supported: ")[1]  # a serial port: pyserial's only
    config = tmp_path / "points.toml"
    config.write_text(
        '[[bus]]\nname = "b"\nport = "quic://127.0.0.1:502"\n\n'
        '[[point]]\nname = "x"\nbus = "b"\nslave = 1\ntable = "holding"\naddress = 0\n'
    )
    r = pyrtu("poll", "--config", config, "--duration", "1")
    assert r.code == 2
    assert f'{config.name}:3: bus[0] ("b"): port: unsupported scheme quic://' in r.err, r.err


def test_the_api_refuses_a_scheme_before_opening_anything() -> None:
    with pytest.raises(ValueError, match=r"^quic://h:1: unsupported scheme quic://; supported: "):
        pyrtu_api.Master("quic://h:1")
    with pytest.raises(ValueError, match="unsupported scheme tcp://"):
        open_port("tcp://127.0.0.1:502")  # a serial port: Master opens tcp://


# -- the busy message --------------------------------------------------------------------------


def test_the_poller_does_not_tell_a_cli_user_to_pass_exclusive_false(tmp_path: Path) -> None:
    """``pyrtu poll --config`` has no way to share a port: its busy message gives no
    Python keyword; the API's keeps its advice, a command with --no-exclusive its flag."""
    with VirtualBus(2, parity="N") as vbus:
        path = vbus.paths[1]
        held = open_port(path, parity="N")
        try:
            with pytest.raises(PortBusyError, match=r"pass exclusive=False to share it\)$"):
                open_port(path, parity="N")
            config = tmp_path / "points.toml"
            config.write_text(
                f'[[bus]]\nname = "b"\nport = "{path}"\nparity = "N"\n\n'
                '[[point]]\nname = "x"\nbus = "b"\nslave = 1\ntable = "holding"\naddress = 0\n'
            )
            r = pyrtu("poll", "--config", config, "--duration", "1", "--json")
            assert r.code == 3, r.err
            events = [d for d in r.json_lines() if d.get("event") == "port"]
            assert events[0]["error"] == (
                "busy: another program holds it (ports are opened exclusively)"
            ), events
            assert "exclusive=False" not in r.out + r.err
            cli = pyrtu("read", path, "0", "--parity", "N")
            assert cli.code == 3 and "use --no-exclusive to share it" in cli.err
            assert "exclusive=False" not in cli.err
            gateway = ("gateway", "--listen", "127.0.0.1:0", "--port", path, "-P", "N", "-d", "1")
            refused = pyrtu(*gateway)  # served on, the bus reported not available (#27.4)
            assert refused.code == 0 and "is not available" in refused.err, refused.err
            assert "use --no-exclusive to share it" in refused.err, refused.err
            shared = pyrtu(*gateway, "--no-exclusive")  # the advice holds: it shares the port
            assert shared.code == 0, shared.err
        finally:
            held.close()


def test_busy_advice_is_chosen_by_the_caller() -> None:
    """The API's words by default; a command's: its flag, or none without one."""
    from pyrtu.cli.common import in_cli_terms

    busy = PortBusyError("/dev/ttyX")
    assert str(busy).endswith("(ports are opened exclusively; pass exclusive=False to share it)")
    assert isinstance(busy, PortError) and isinstance(busy, OSError)
    flag = in_cli_terms(busy, shares=True)
    assert str(flag) == (
        "/dev/ttyX: busy: another program holds it "
        "(ports are opened exclusively; use --no-exclusive to share it)"
    )
    none = in_cli_terms(busy, shares=False)
    assert str(none) == "/dev/ttyX: busy: another program holds it (ports are opened exclusively)"
