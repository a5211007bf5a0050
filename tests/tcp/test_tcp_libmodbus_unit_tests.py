"""libmodbus's own ``unit-test-client`` (Debian's libmodbus-dev examples) against
pyrtu's `TcpServer`, in its ``tcp`` and ``tcppi`` (IPv6) modes: every assertion.

The client expects ``unit-test-server.c``: its register map (unit-test.h) and a few
deliberate misbehaviours.  Here the map is a pyrtu `DataStore` behind pyrtu's own
slave logic (`SlaveBase`, the standard functions and their exceptions) and
`TcpServer`; the misbehaviours are emulated where they live in the original:

* in the application (what ``unit-test-server`` answers on purpose): a read of
  UT_REGISTERS_NB_SPECIAL registers answered with one fewer, exception 6 (busy)
  at UT_REGISTERS_ADDRESS_SPECIAL, exception 3 for the write-coil / write-register
  requests it replies to with a wrong length;
* in a small proxy in front of the server (what a Modbus server never does by
  itself): an answer sent 0.5 s late, one with a wrong transaction id, one sent a
  byte every 5 ms.

Messaging on TCP/IP Implementation Guide 4.4.1.2 is what it checks of the unit ids:
the client's default unit is 0xFF, it asserts an answer to unit 0 ("2/3 Reply after
a query with unit id == 0"), and one to unit 18 (``INVALID_SERVER_ID``, which a
libmodbus TCP server answers whatever the unit): this server serves 17 and 18.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from peers.tools import free_tcp_port

from pyrtu import DataStore, MbapFramer
from pyrtu.core.line import LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.tcp.server import TcpServer

EXAMPLES = Path("/usr/share/doc/libmodbus-dev/examples")

# unit-test.h
SERVER_ID, INVALID_SERVER_ID = 17, 18
UT_BITS_ADDRESS, UT_BITS_NB = 0x130, 0x25
UT_BITS_ADDRESS_INVALID_REQUEST_LENGTH = UT_BITS_ADDRESS + 2
UT_INPUT_BITS_ADDRESS, UT_INPUT_BITS_NB = 0x1C4, 0x16
UT_INPUT_BITS_TAB = bytes((0xAC, 0xDB, 0x35))
UT_REGISTERS_ADDRESS, UT_REGISTERS_NB_MAX = 0x160, 0x20
UT_REGISTERS_ADDRESS_SPECIAL = 0x170
UT_REGISTERS_ADDRESS_INVALID_TID_OR_SLAVE = 0x171
UT_REGISTERS_ADDRESS_SLEEP_500_MS = 0x172
UT_REGISTERS_ADDRESS_BYTE_SLEEP_5_MS = 0x173
UT_REGISTERS_NB_SPECIAL = 0x2
UT_INPUT_REGISTERS_ADDRESS, UT_INPUT_REGISTERS_TAB = 0x108, [0x000A]


def build_client(where: Path, port: int) -> Path:
    """unit-test-client compiled with ``port`` in place of its fixed 1502."""
    if not (EXAMPLES / "unit-test-client.c").exists() or shutil.which("gcc") is None:
        pytest.fail("needs libmodbus-dev (its examples) and gcc: apt-get install libmodbus-dev gcc")
    source = (EXAMPLES / "unit-test-client.c").read_text()
    assert source.count("1502") == 2  # modbus_new_tcp and modbus_new_tcp_pi
    (where / "unit-test-client.c").write_text(source.replace("1502", str(port)))
    shutil.copy(EXAMPLES / "unit-test.h", where / "unit-test.h")
    flags = subprocess.run(
        ["pkg-config", "--cflags", "--libs", "libmodbus"],
        capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    binary = where / "unit-test-client"
    subprocess.run(
        ["gcc", "-O1", "-w", "-o", str(binary), str(where / "unit-test-client.c"), *flags],
        check=True, capture_output=True,
    )  # fmt: skip
    return binary


class UnitTestApplication:
    """unit-test-server.c's application: its map in a DataStore, pyrtu's slave
    logic, and its deliberate answers (module docstring)."""

    def __init__(self) -> None:
        store = DataStore()
        store.coils.add_range(UT_BITS_ADDRESS, [False] * UT_BITS_NB)
        bits = [bool(UT_INPUT_BITS_TAB[i // 8] >> (i % 8) & 1) for i in range(UT_INPUT_BITS_NB)]
        store.discrete_inputs.add_range(UT_INPUT_BITS_ADDRESS, bits)
        store.holding_registers.add_range(UT_REGISTERS_ADDRESS, [0] * UT_REGISTERS_NB_MAX)
        store.input_registers.add_range(UT_INPUT_REGISTERS_ADDRESS, UT_INPUT_REGISTERS_TAB)
        # FC 17: the client asserts 10 bytes with the run indicator (0xFF) second
        self.slave = SlaveBase(
            [SERVER_ID, INVALID_SERVER_ID], store, line=LineConfig(),
            server_id=b"\xb4\xffpyrtu-u",
        )  # fmt: skip
        self.addresses = self.slave.addresses

    def execute(self, unit: int, request: bytes) -> bytes | None:
        fc = request[0]
        address = int.from_bytes(request[1:3], "big") if len(request) >= 3 else -1
        if fc == 3 and len(request) == 5:
            if int.from_bytes(request[3:5], "big") == UT_REGISTERS_NB_SPECIAL:
                request = request[:3] + (UT_REGISTERS_NB_SPECIAL - 1).to_bytes(2, "big")
            elif address == UT_REGISTERS_ADDRESS_SPECIAL:
                return bytes((0x83, 0x06))  # server device busy
        elif (fc, address) in (
            (5, UT_BITS_ADDRESS_INVALID_REQUEST_LENGTH),
            (6, UT_REGISTERS_ADDRESS_SPECIAL),
        ):
            return bytes((fc | 0x80, 0x03))  # its reply with a wrong length: 3
        return self.slave.execute(unit, request)


def _drip(writer: asyncio.StreamWriter, adu: bytes) -> None:
    """A byte every 5 ms, as unit-test-server's usleep(5000) loop: from a thread on a
    duplicate of the socket (an event-loop timer wakes later under load; the client
    passes its 7 ms byte timeout only with gaps under 7 ms, fails its 3 ms one)."""
    sock = writer.get_extra_info("socket")
    with socket.socket(fileno=os.dup(sock.fileno())) as dup:
        for i in range(len(adu)):
            time.sleep(0.005)
            dup.send(adu[i : i + 1])


async def _proxy(
    client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter, server: tuple[str, int]
) -> None:
    """Bytes both ways; answers to the special reads late, with a wrong transaction
    id, or a byte every 5 ms (module docstring)."""
    server_r, server_w = await asyncio.open_connection(*server)
    special: dict[int, int] = {}  # transaction id -> address of an FC 03 request

    async def up() -> None:
        framer = MbapFramer("slave")
        while data := await client_r.read(65536):
            framer.receive_data(data)
            while (ev := framer.next_event()) is not None:
                if ev.error is None and ev.pdu[0] == 3 and len(ev.pdu) == 5:
                    special[ev.transaction] = int.from_bytes(ev.pdu[1:3], "big")
            server_w.write(data)
        server_w.close()

    async def down() -> None:
        framer = MbapFramer("master")
        while data := await server_r.read(65536):
            framer.receive_data(data)
            while (ev := framer.next_event()) is not None:
                adu = ev.adu
                address = special.pop(ev.transaction, None)
                if address == UT_REGISTERS_ADDRESS_SLEEP_500_MS:
                    await asyncio.sleep(0.5)
                elif address == UT_REGISTERS_ADDRESS_INVALID_TID_OR_SLAVE:
                    adu = ((ev.transaction + 1) & 0xFFFF).to_bytes(2, "big") + adu[2:]
                elif address == UT_REGISTERS_ADDRESS_BYTE_SLEEP_5_MS:
                    await client_w.drain()
                    await asyncio.to_thread(_drip, client_w, adu)
                    continue
                client_w.write(adu)
        client_w.close()

    await asyncio.gather(up(), down(), return_exceptions=True)


@pytest.fixture
def unit_test_server() -> Iterator[tuple[int, TcpServer]]:
    """The server on 127.0.0.1 and ::1 (a free port), through the proxy."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = TcpServer(UnitTestApplication())
    port = free_tcp_port()

    async def start() -> list[asyncio.Server]:
        await server.start("127.0.0.1", 0)
        assert server.address is not None
        back = server.address
        return [
            await asyncio.start_server(lambda r, w: _proxy(r, w, back), host, port)
            for host in ("127.0.0.1", "::1")
        ]

    proxies = asyncio.run_coroutine_threadsafe(start(), loop).result(10)
    try:
        yield port, server
    finally:

        async def stop() -> None:
            for p in proxies:
                p.close()
            await server.close()

        asyncio.run_coroutine_threadsafe(stop(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


@pytest.mark.wall_clock  # the client's byte timeouts: 3 ms must fail, 7 ms pass (5 ms/byte)
@pytest.mark.parametrize("mode", ["tcp", "tcppi"])
def test_libmodbus_unit_test_client_passes_every_assertion(
    mode: str, unit_test_server: tuple[int, TcpServer], tmp_path: Path
) -> None:
    port, server = unit_test_server
    client = build_client(tmp_path, port)
    done = subprocess.run(
        [str(client), mode],
        capture_output=True,
        text=True,
        errors="replace",
        timeout=120,
        check=False,
    )
    out = done.stdout
    assertions = [line for line in out.splitlines() if line.rstrip().endswith("OK")]
    assert done.returncode == 0 and "ALL TESTS PASS WITH SUCCESS" in out, out[-3000:]
    assert "assertion error" not in out
    assert "2/3 Reply after a query with unit id == 0: OK" in out
    assert "1/3 Response from slave 18: OK" in out
    assert len(assertions) >= 100, len(assertions)
    print(f"{mode}: {len(assertions)} assertions OK")
    assert server.counters["bad_headers"] == 0
