"""tmodbus (an independent Modbus/TCP Security implementation) as the client, run in its
own Python >= 3.12 environment: ``python tmodbus_client.py HOST PORT CERT KEY CA OPS``.
OPS is JSON: a list of ["read", address, count] or ["write", address, value]; prints
one JSON line per op: {"ok": registers or true} or {"exception": its class name}."""

import asyncio
import json
import ssl
import sys

from tmodbus import create_async_tcp_client
from tmodbus.exceptions import ModbusResponseError


async def main() -> None:
    host, port, cert, key, ca, ops = sys.argv[1:7]
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(cert, key)
    context.load_verify_locations(cafile=ca)
    client = create_async_tcp_client(
        host,
        int(port),
        unit_id=1,
        timeout=5.0,
        connect_timeout=5.0,
        auto_reconnect=False,
        retry_on_device_busy=False,
        ssl=context,
        server_hostname=host,
    )
    async with client:
        for op, address, arg in json.loads(ops):
            try:
                if op == "read":
                    result = list(await client.read_holding_registers(address, arg))
                else:
                    await client.write_single_register(address, arg)
                    result = True
                print(json.dumps({"ok": result}), flush=True)
            except ModbusResponseError as exc:
                print(json.dumps({"exception": type(exc).__name__}), flush=True)


asyncio.run(main())
