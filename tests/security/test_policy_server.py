"""The access policy and the audit trail on `TcpServer` over real sockets: a request
outside the policy is answered exception 01, never reaches the DataStore, is counted
and logged once per client and reason; every executed write is one JSON line.
Clients: pymodbus (an independent peer) and raw sockets whose frames are built with
`struct` ([TCP] 3.1.3 MBAP header), bound to 127.0.0.1 or 127.0.0.2 (two clients
the policy tells apart by address)."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import struct
import time
from pathlib import Path

import pytest

from pyrtu import DataStore
from pyrtu.security import AuditTrail, Decision, Identity, Policy, parse_policy
from pyrtu.tcp.server import TcpServer

POLICY = """\
[[rule]]
name = "local"
clients = ["127.0.0.1"]
units = "1"
holding_registers = "0-9"

[[rule]]
name = "neighbour"
clients = ["127.0.0.2/32"]
read_only = true
"""


def store() -> DataStore:
    s = DataStore()
    s.holding_registers.add_range(0, list(range(100, 120)))
    s.coils.add_range(0, [False] * 8)
    return s


def transact(source: str, port: int, tid: int, unit: int, pdu: bytes) -> bytes:
    """One request from ``source``; the whole answer ADU."""
    with socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(source, 0)) as s:
        s.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
        header = b""
        while len(header) < 7:
            chunk = s.recv(7 - len(header))
            assert chunk, "closed"
            header += chunk
        length = struct.unpack(">H", header[4:6])[0]
        body = b""
        while len(body) < length - 1:
            chunk = s.recv(length - 1 - len(body))
            assert chunk, "closed"
            body += chunk
        return header + body


def refused(tid: int, unit: int, function: int) -> bytes:
    """Exception 01 ([AP] 7) in an MBAP frame echoing tid and unit."""
    return struct.pack(">HHHBBB", tid, 0, 3, unit, function | 0x80, 1)


class Server:
    def __init__(self, loop: asyncio.AbstractEventLoop, server: TcpServer) -> None:
        self.loop, self.server = loop, server
        asyncio.run_coroutine_threadsafe(server.start("127.0.0.1", 0), loop).result(10)
        assert server.address is not None
        self.port = server.address[1]

    def stats(self) -> dict[str, object]:
        async def get() -> dict[str, object]:
            return self.server.stats()

        return asyncio.run_coroutine_threadsafe(get(), self.loop).result(10)

    def close(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(10)


def test_requests_outside_the_policy_get_exception_01_and_change_nothing(
    loop: asyncio.AbstractEventLoop, caplog: pytest.LogCaptureFixture
) -> None:
    data = store()
    denied: list[tuple[Identity, Decision]] = []
    server = Server(
        loop,
        TcpServer.for_store(
            1,
            data,
            policy=parse_policy(POLICY, "p.toml"),
            on_denied=lambda who, why: denied.append((who, why)),
        ),
    )
    caplog.set_level(logging.WARNING, "pyrtu.gateway")
    try:
        write9 = struct.pack(">BHH", 6, 9, 0xBEEF)  # the last address of the range
        assert (
            transact("127.0.0.1", server.port, 1, 1, write9)
            == struct.pack(">HHHB", 1, 0, 6, 1) + write9
        )
        write10 = struct.pack(">BHH", 6, 10, 0xBEEF)  # one past it
        for tid in (2, 3, 4):  # thrice: counted thrice, logged once
            assert transact("127.0.0.1", server.port, tid, 1, write10) == refused(tid, 1, 6)
        read = struct.pack(">BHH", 3, 0, 1)
        assert transact("127.0.0.1", server.port, 5, 255, read) == refused(5, 255, 3)  # unit
        # the neighbour reads anything, writes nothing
        answer = transact("127.0.0.2", server.port, 6, 1, struct.pack(">BHH", 3, 15, 2))
        assert answer == struct.pack(">HHHBBBHH", 6, 0, 7, 1, 3, 4, 115, 116)
        coil = struct.pack(">BHH", 5, 0, 0xFF00)
        assert transact("127.0.0.2", server.port, 7, 1, coil) == refused(7, 1, 5)
        assert data.holding_registers.get(9) == 0xBEEF
        assert data.holding_registers.get(10) == 110  # never written
        assert data.coils.get(0) is False
        stats = server.stats()
        assert stats["denied"] == 5
        assert stats["denied_by"] == {"address": 3, "unit": 1, "read_only": 1}
    finally:
        server.close()
    lines = [r.getMessage() for r in caplog.records if "refused (exception 01)" in r.getMessage()]
    assert len(lines) == 3, lines  # once per client and reason
    assert [who.address for who, _ in denied] == ["127.0.0.1", "127.0.0.1", "127.0.0.2"]


def test_pymodbus_client_sees_exception_01(loop: asyncio.AbstractEventLoop) -> None:
    from pymodbus.client import ModbusTcpClient

    data = store()
    server = Server(loop, TcpServer.for_store(1, data, policy=Policy.read_only()))
    client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
    try:
        assert client.connect()
        assert client.read_holding_registers(0, count=3, device_id=1).registers == [100, 101, 102]
        rr = client.write_registers(0, [7, 8], device_id=1)
        assert rr.isError() and rr.exception_code == 1
        rr = client.write_coil(0, True, device_id=1)
        assert rr.isError() and rr.exception_code == 1
        assert data.holding_registers.get(0) == 100 and data.coils.get(0) is False
    finally:
        client.close()
        server.close()


def test_audit_trail_records_every_executed_write(
    loop: asyncio.AbstractEventLoop, tmp_path: Path
) -> None:
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "audit.jsonl"
    trail = AuditTrail.open(path)
    data = store()
    server = Server(loop, TcpServer.for_store(1, data, audit=trail))
    client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
    before = time.time()
    try:
        assert client.connect()
        client.read_holding_registers(0, count=2, device_id=1)  # a read: not recorded
        assert not client.write_registers(3, [7, 65535], device_id=1).isError()
        assert not client.write_coils(1, [True, False, True], device_id=1).isError()
        assert not client.write_register(4, 9, device_id=1).isError()
        rr = client.write_register(500, 1, device_id=1)  # no such address: 0x02
        assert rr.isError() and rr.exception_code == 2
        stats = server.stats()
    finally:
        client.close()
        server.close()
        trail.close()
    records = [json.loads(line) for line in path.read_text().splitlines()]
    local_port = records[0]["port"]
    assert [
        {k: v for k, v in r.items() if k not in ("time", "port")} for r in records
    ] == [
        {"client": "127.0.0.1", "unit": 1, "function": 16, "name": "write_registers",
         "address": 3, "values": [7, 65535], "result": "ok"},
        {"client": "127.0.0.1", "unit": 1, "function": 15, "name": "write_coils",
         "address": 1, "values": [True, False, True], "result": "ok"},
        {"client": "127.0.0.1", "unit": 1, "function": 6, "name": "write_register",
         "address": 4, "values": [9], "result": "ok"},
        {"client": "127.0.0.1", "unit": 1, "function": 6, "name": "write_register",
         "address": 500, "values": [1], "result": "exception 0x02"},
    ]  # fmt: skip
    assert all(r["port"] == local_port for r in records) and isinstance(local_port, int)
    for r in records:  # ISO 8601 UTC, between the start and now
        from datetime import datetime

        stamp = datetime.fromisoformat(r["time"]).timestamp()
        assert before - 1 <= stamp <= time.time() + 1 and r["time"].endswith("+00:00")
    assert stats["audited_writes"] == 4


def test_refusals_and_audited_writes_in_the_prometheus_text(
    loop: asyncio.AbstractEventLoop, tmp_path: Path
) -> None:
    from prometheus_client import CollectorRegistry, generate_latest
    from prometheus_client.parser import text_string_to_metric_families

    from pyrtu.metrics.gateway import counter_families

    trail = AuditTrail.open(tmp_path / "audit.jsonl")
    server = Server(
        loop,
        TcpServer.for_store(1, store(), policy=parse_policy(POLICY, "p.toml"), audit=trail),
    )
    try:
        transact("127.0.0.2", server.port, 1, 1, struct.pack(">BHH", 6, 0, 1))  # read_only
        transact("127.0.0.3", server.port, 2, 1, struct.pack(">BHH", 3, 0, 1))  # no rule
        transact("127.0.0.1", server.port, 3, 1, struct.pack(">BHH", 6, 0, 1))  # executed
        stats = server.stats()
    finally:
        server.close()
        trail.close()

    class Collector:
        def collect(self):  # type: ignore[no-untyped-def]
            return counter_families("pyrtu_simulate_tcp", stats)

    registry = CollectorRegistry()
    registry.register(Collector())  # type: ignore[arg-type]
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(generate_latest(registry).decode())
        for s in family.samples
    }
    denied = {
        dict(labels)["reason"]: value
        for (name, labels), value in samples.items()
        if name == "pyrtu_simulate_tcp_denied_total"
    }
    assert denied == {"no_rule": 1, "unit": 0, "function": 0, "read_only": 1, "table": 0,
                      "address": 0, "unplaceable": 0}  # fmt: skip
    assert samples[("pyrtu_simulate_tcp_audited_writes_total", ())] == 1
