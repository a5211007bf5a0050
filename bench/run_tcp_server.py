"""One Modbus TCP server of bench/bench_tcp_server.py, in a process of its own.

    python bench/run_tcp_server.py pyrtu|pymodbus|floor [--unit 1] [--port 0]

``pyrtu``: ``TcpServer.for_store`` (pyrtu.tcp.server) on the C core (``backend="c"``;
the process exits 1 if the C core is missing), serving one DataStore filled with
the register pattern of tests/peers/pattern.py for unit ``--unit``;
``pymodbus``: pymodbus's ``ModbusTcpServer`` (its asyncio server) serving the same
tables (tests/peers/pymodbus_server.py's ``make_device``), without the request
counting hook the interop peer adds, so pymodbus runs as a user would run it.

``floor``: no Modbus server at all, the least any asyncio server does per request:
an ``asyncio.Protocol`` whose ``data_received`` takes one whole request for the
benchmark's one read (FC 03, 10 holding registers from 0, unit ``--unit``) and
writes its answer, built once from the pattern with ``struct``, behind the
request's transaction id (anything else closes the connection).

All on asyncio's default event loop (``asyncio.run``), on 127.0.0.1, port
``--port`` (0: a free one).  Prints ``READY <port> <server> <detail>`` once it
listens, serves until SIGTERM or SIGINT, then prints ``STATS <key=value ...>``
(pyrtu: its counters; floor: the requests it answered; pymodbus: nothing it
counts) and exits 0.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import struct
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

HOST = "127.0.0.1"


async def _until_signalled() -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()


async def serve_pyrtu(unit: int, port: int) -> None:
    from peers import pattern

    import pyrtu
    from pyrtu.tcp.server import TcpServer

    if "c" not in pyrtu.available_backends():
        raise SystemExit("run_tcp_server.py: the C core is not available (build it first)")
    server = TcpServer.for_store(unit, pattern.pattern_store(unit), backend="c")
    async with await server.start(HOST, port):
        bound = server.address
        assert bound is not None
        print(f"READY {bound[1]} pyrtu backend=c", flush=True)
        await _until_signalled()
        counters = server.counters
    print("STATS " + " ".join(f"{k}={v}" for k, v in sorted(counters.items())), flush=True)


async def serve_pymodbus(unit: int, port: int) -> None:
    from peers.pymodbus_server import make_device
    from pymodbus import __version__ as pymodbus_version
    from pymodbus.server import ModbusTcpServer

    server = ModbusTcpServer([make_device(unit)], address=(HOST, port))
    await server.serve_forever(background=True)
    transport = server.transport
    assert transport is not None
    bound = transport.sockets[0].getsockname()  # type: ignore[attr-defined]
    print(f"READY {bound[1]} pymodbus {pymodbus_version}", flush=True)
    await _until_signalled()
    await server.shutdown()  # type: ignore[no-untyped-call]
    print("STATS", flush=True)


async def serve_floor(unit: int, port: int) -> None:
    from peers import pattern

    count = 10
    # [TCP] 3.1.3 / [AP] 6.3: the request FC 03 from 0, 10 registers; its answer's
    # PDU: 03, the byte count, the registers big-endian
    request = struct.pack(">HHBBHH", 0, 6, unit, 3, 0, count)
    answer_pdu = struct.pack(f">BB{count}H", 3, 2 * count, *pattern.holdings(unit, 0, count))
    answer_tail = struct.pack(">HHB", 0, 1 + len(answer_pdu), unit) + answer_pdu
    answered = 0

    class Floor(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            assert isinstance(transport, asyncio.Transport)
            self.transport = transport

        def data_received(self, data: bytes) -> None:
            nonlocal answered
            if len(data) != 12 or data[2:] != request:
                self.transport.close()
                return
            self.transport.write(data[:2] + answer_tail)
            answered += 1

    loop = asyncio.get_running_loop()
    server = await loop.create_server(Floor, HOST, port)
    bound = server.sockets[0].getsockname()
    print(f"READY {bound[1]} floor asyncio", flush=True)
    await _until_signalled()
    server.close()
    print(f"STATS answers={answered}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("server", choices=("pyrtu", "pymodbus", "floor"))
    ap.add_argument("--unit", type=int, default=1, help="the unit id served (1..247)")
    ap.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: a free one)")
    args = ap.parse_args(argv)
    if not 1 <= args.unit <= 247:
        ap.error(f"--unit: a unit id is 1..247, not {args.unit}")
    if not 0 <= args.port <= 65535:
        ap.error(f"--port: 0..65535, not {args.port}")
    serve = {"pyrtu": serve_pyrtu, "pymodbus": serve_pymodbus, "floor": serve_floor}[args.server]
    asyncio.run(serve(args.unit, args.port))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
