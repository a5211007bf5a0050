"""tmodbus as the Modbus/TCP Security server, run in its own Python >= 3.12
environment: ``python tmodbus_server.py CERT KEY CA``.  Holding registers 0..9 (value
100 + address) at unit 1; the role of the client's certificate decides: "operator"
reads and writes, "viewer" reads, any other role (or none) gets exception 01, as the
specification says.  Prints {"port": N} once it listens, then one JSON line per
write it executed; stops on SIGTERM."""

import asyncio
import json
import signal
import ssl
import sys

from tmodbus.exceptions import IllegalFunctionError
from tmodbus.pdu import ReadHoldingRegistersPDU, WriteSingleRegisterPDU
from tmodbus.server import AsyncTcpServer, ModbusRequestRouter, extract_modbus_role
from tmodbus.server.handler import RequestContext

REGISTERS = [100 + a for a in range(10)]


def role_of(context: RequestContext) -> str | None:
    return extract_modbus_role(context.client_cert) if context.client_cert else None


async def main() -> None:
    cert, key, ca = sys.argv[1:4]
    tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    tls.load_cert_chain(cert, key)
    tls.load_verify_locations(cafile=ca)
    tls.verify_mode = ssl.CERT_REQUIRED
    tls.minimum_version = ssl.TLSVersion.TLSv1_2
    router = ModbusRequestRouter()

    @router.register(ReadHoldingRegistersPDU, unit_id=1)
    async def read(
        unit: int, request: ReadHoldingRegistersPDU, context: RequestContext
    ) -> list[int]:
        if role_of(context) not in ("operator", "viewer"):
            raise IllegalFunctionError(request.function_code)
        return REGISTERS[request.start_address : request.start_address + request.quantity]

    @router.register(WriteSingleRegisterPDU, unit_id=1)
    async def write(unit: int, request: WriteSingleRegisterPDU, context: RequestContext) -> int:
        if role_of(context) != "operator":
            raise IllegalFunctionError(request.function_code)
        REGISTERS[request.address] = request.value
        print(
            json.dumps({"wrote": [request.address, request.value], "role": role_of(context)}),
            flush=True,
        )
        return request.value

    server = AsyncTcpServer("127.0.0.1", router, port=0, ssl_context=tls)
    await server.start()
    port = server._server.sockets[0].getsockname()[1]
    print(json.dumps({"port": port}), flush=True)
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    await stop.wait()
    await server.stop()


asyncio.run(main())
