"""A pymodbus 3.x serial RTU server serving the pattern of `pattern.py`.

    python tests/peers/pymodbus_server.py PORT SLAVE [--baud N] [--ascii]
    python tests/peers/pymodbus_server.py HOST:PORT SLAVE --tcp

``--tcp``: a Modbus TCP server (ModbusTcpServer) on HOST:PORT instead, serving
unit SLAVE (and the unit ids 0 and 255 some clients use for a plain server).

Opens PORT as 8N1 (pseudo-terminals refuse parity) and serves slave address
SLAVE only; requests for other addresses are ignored, as on a shared bus.

pymodbus 3.16's server does not do that by itself: with SimDevice (and with the
deprecated ModbusServerContext, which it converts) a request for an unknown
address hits a ``KeyError`` in ``SimCore.__get_device`` instead of
``NoSuchIdException``, so ``ignore_missing_devices`` has no effect and the server
answers other slaves' requests with exception 4 (and logs a traceback).  The
``trace_pdu`` hook below drops requests for other addresses before they reach
the datastore (broadcasts, address 0, still go through).

Prints ``READY <port> <slave>`` once the port is open and exits on SIGTERM or
SIGINT, printing ``STATS requests=R responses=A ignored=I`` (the frames its
framer decoded: for it, answered, for other slaves; "stray" counts answers sent
without a request for it, e.g. pymodbus's exception 1 to undecodable garbage).
Uses the SimDevice/SimData model of pymodbus >= 3.10 (four separate tables, one
bit per coil address).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pattern
from pymodbus import FramerType
from pymodbus import __version__ as pymodbus_version
from pymodbus.pdu import ModbusPDU
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

#: FC 43/14 basic objects (VendorName, ProductCode, MajorMinorRevision)
IDENTITY = {0: "pymodbus-peer", 1: "PYRTU-INTEROP", 2: pymodbus_version}


def make_device(slave: int) -> SimDevice:
    """The four tables of `slave`, filled with the pattern."""
    return SimDevice(
        id=slave,
        simdata=(
            [SimData(0, values=pattern.coils(slave, 0, pattern.N_BITS), datatype=DataType.BITS)],
            [
                SimData(
                    0, values=pattern.discretes(slave, 0, pattern.N_BITS), datatype=DataType.BITS
                )
            ],
            [
                SimData(
                    0,
                    values=pattern.holdings(slave, 0, pattern.N_REGS),
                    datatype=DataType.REGISTERS,
                )
            ],
            [
                SimData(
                    0, values=pattern.inputs(slave, 0, pattern.N_REGS), datatype=DataType.REGISTERS
                )
            ],
        ),
    )


async def serve(port: str, slave: int, baudrate: int, ascii_mode: bool = False) -> None:
    def on_connect(connected: bool) -> None:
        if connected:
            print(f"READY {port} {slave} pymodbus {pymodbus_version}", flush=True)

    stats = {"requests": 0, "responses": 0, "ignored": 0, "stray": 0}
    pending = [0]

    def only_ours(sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        if sending:
            stats["responses"] += 1
            if pending[0]:
                pending[0] -= 1
            else:
                stats["stray"] += 1
                print(f"stray answer: {pdu}", file=sys.stderr, flush=True)
            return pdu
        if pdu.dev_id in (0, slave):
            stats["requests"] += 1
            pending[0] += pdu.dev_id != 0
            return pdu
        stats["ignored"] += 1
        return None  # another slave's request: stay silent (see the module docstring)

    server = ModbusSerialServer(
        make_device(slave),
        framer=FramerType.ASCII if ascii_mode else FramerType.RTU,
        port=port,
        baudrate=baudrate,
        parity="N",
        bytesize=8,
        stopbits=1,
        identity=ModbusDeviceIdentification(info=dict(IDENTITY)),  # type: ignore[no-untyped-call]
        ignore_missing_devices=True,
        broadcast_enable=True,
        trace_connect=on_connect,
        trace_pdu=only_ours,  # type: ignore[arg-type]  # None drops the request
    )
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, lambda: asyncio.ensure_future(server.shutdown()))  # type: ignore[no-untyped-call]
    await server.serve_forever()
    print("STATS " + " ".join(f"{k}={v}" for k, v in stats.items()), flush=True)


async def serve_tcp(address: str, slave: int) -> None:
    host, _, port = address.rpartition(":")
    stats = {"requests": 0, "responses": 0}

    def count(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        stats["responses" if sending else "requests"] += 1
        return pdu

    server = ModbusTcpServer(
        [make_device(slave), make_device_as(slave, 255)],
        address=(host, int(port)),
        identity=ModbusDeviceIdentification(info=dict(IDENTITY)),  # type: ignore[no-untyped-call]
        trace_pdu=count,
    )
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, lambda: asyncio.ensure_future(server.shutdown()))  # type: ignore[no-untyped-call]
    await server.serve_forever(background=True)
    print(f"READY {address} {slave} pymodbus {pymodbus_version}", flush=True)
    with contextlib.suppress(asyncio.CancelledError):
        await server.serving
    print("STATS " + " ".join(f"{k}={v}" for k, v in stats.items()), flush=True)


def make_device_as(slave: int, unit: int) -> SimDevice:
    """The tables of `slave` under another unit id."""
    device = make_device(slave)
    device.id = unit
    return device


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port")
    parser.add_argument("slave", type=int)
    parser.add_argument("--baud", type=int, default=115200)
    parser.add_argument("--ascii", action="store_true", help="Modbus ASCII instead of RTU")
    parser.add_argument("--tcp", action="store_true", help="Modbus TCP on HOST:PORT")
    args = parser.parse_args(argv)
    if not 1 <= args.slave <= 247:
        parser.error("slave must be 1..247")
    if args.tcp:
        asyncio.run(serve_tcp(args.port, args.slave))
        return 0
    asyncio.run(serve(args.port, args.slave, args.baud, args.ascii))
    return 0


if __name__ == "__main__":
    sys.exit(main())
