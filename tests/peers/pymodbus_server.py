"""A pymodbus 3.x serial RTU server serving the pattern of `pattern.py`.

    python tests/peers/pymodbus_server.py PORT SLAVE [--baud N] [--ascii]
    python tests/peers/pymodbus_server.py HOST:PORT SLAVE --tcp

``--tcp``: a Modbus TCP server (ModbusTcpServer) on HOST:PORT instead, serving
unit SLAVE (and the unit ids 0 and 255 some clients use for a plain server);
``--udp``: the same over UDP (ModbusUdpServer: one MBAP ADU per datagram).

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
Uses the SimDevice/SimData model of pymodbus >= 3.12 (four separate tables, one
bit per coil address); on 3.9 to 3.11, which lack it (no ``DataType``), the same
tables as a ``ModbusServerContext`` of one device context (`make_device`).
`DEVICE_KW` and `server_options` are the other names that differ between the pymodbus
releases pyrtu.compat is tested with (tests/compat/).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import inspect
import signal
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pattern
import pymodbus.simulator
from pymodbus import FramerType
from pymodbus import __version__ as pymodbus_version
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer, ModbusUdpServer

try:  # pymodbus >= 3.10
    from pymodbus.pdu.device import ModbusDeviceIdentification
except ImportError:  # 3.9
    from pymodbus.device import ModbusDeviceIdentification  # type: ignore[no-redef]

#: FC 43/14 basic objects (VendorName, ProductCode, MajorMinorRevision)
IDENTITY = {0: "pymodbus-peer", 1: "PYRTU-INTEROP", 2: pymodbus_version}

#: the keyword of pymodbus's client calls naming the device: ``slave=`` up to 3.9,
#: ``device_id=`` from 3.10 (pymodbus #2600)
DEVICE_KW = (
    "device_id"
    if "device_id" in inspect.signature(ModbusClientMixin.read_coils).parameters
    else "slave"
)
#: SimDevice/SimData/DataType as the server's datastore (pymodbus >= 3.12)
SIM_DEVICES = hasattr(pymodbus.simulator, "DataType")


def server_options() -> dict[str, Any]:
    """``ignore_missing_devices=True`` (``ignore_missing_slaves`` up to 3.9)."""
    params = inspect.signature(ModbusSerialServer.__init__).parameters
    name = (
        "ignore_missing_slaves" if "ignore_missing_slaves" in params else "ignore_missing_devices"
    )
    return {name: True}


def tables_device(
    slave: int,
    coils: list[bool] | None = None,
    discretes: list[bool] | None = None,
    holdings: list[int] | None = None,
    inputs: list[int] | None = None,
) -> Any:
    """A pymodbus datastore serving the given tables (each from address 0) for device
    ``slave``, in the model the installed pymodbus has: a SimDevice (>= 3.12) or a
    ModbusServerContext (3.9 to 3.11)."""
    if SIM_DEVICES:
        from pymodbus.simulator import DataType, SimData, SimDevice

        def table(values: list[Any] | None, kind: Any) -> list[Any]:
            return [SimData(0, values=values, datatype=kind)] if values else []

        if coils is None and discretes is None and inputs is None:
            return SimDevice(id=slave, simdata=table(holdings, DataType.REGISTERS))
        return SimDevice(
            id=slave,
            simdata=(
                table(coils, DataType.BITS),
                table(discretes, DataType.BITS),
                table(holdings, DataType.REGISTERS),
                table(inputs, DataType.REGISTERS),
            ),
        )
    from pymodbus import datastore

    # the device context adds 1 to every address: a block from 1 serves address 0
    def block(values: list[Any] | None) -> Any:
        return datastore.ModbusSequentialDataBlock(1, list(values or [0]))

    context_class = getattr(datastore, "ModbusDeviceContext", None) or datastore.ModbusSlaveContext
    device = context_class(
        di=block(discretes), co=block(coils), hr=block(holdings), ir=block(inputs)
    )
    params = inspect.signature(datastore.ModbusServerContext.__init__).parameters
    devices = "devices" if "devices" in params else "slaves"
    return datastore.ModbusServerContext(**{devices: {slave: device}}, single=False)


def make_device(slave: int) -> Any:
    """The four tables of `slave`, filled with the pattern."""
    return tables_device(
        slave,
        coils=pattern.coils(slave, 0, pattern.N_BITS),
        discretes=pattern.discretes(slave, 0, pattern.N_BITS),
        holdings=pattern.holdings(slave, 0, pattern.N_REGS),
        inputs=pattern.inputs(slave, 0, pattern.N_REGS),
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
        broadcast_enable=True,
        **server_options(),
        trace_connect=on_connect,
        trace_pdu=only_ours,  # type: ignore[arg-type]  # None drops the request
    )
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, lambda: asyncio.ensure_future(server.shutdown()))  # type: ignore[no-untyped-call]
    await server.serve_forever()
    print("STATS " + " ".join(f"{k}={v}" for k, v in stats.items()), flush=True)


async def serve_tcp(address: str, slave: int, udp: bool = False) -> None:
    host, _, port = address.rpartition(":")
    stats = {"requests": 0, "responses": 0}

    def count(sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        stats["responses" if sending else "requests"] += 1
        return pdu

    server = (ModbusUdpServer if udp else ModbusTcpServer)(
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


def make_device_as(slave: int, unit: int) -> Any:
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
    parser.add_argument("--udp", action="store_true", help="Modbus over UDP on HOST:PORT")
    args = parser.parse_args(argv)
    if not 1 <= args.slave <= 247:
        parser.error("slave must be 1..247")
    if args.tcp or args.udp:
        asyncio.run(serve_tcp(args.port, args.slave, udp=args.udp))
        return 0
    asyncio.run(serve(args.port, args.slave, args.baud, args.ascii))
    return 0


if __name__ == "__main__":
    sys.exit(main())
