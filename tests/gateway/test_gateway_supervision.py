"""Every background task of the gateway is supervised: a bus worker and the sweeper
are made to raise (a method of the gateway patched to fail: the fault is the
point) while the gateway serves two simulated drives on virtual buses through real
TCP clients, and what the user sees is checked: one log line naming the task and
the cause, one ``on_task`` report (a ``task_failed`` line or message of ``pyrtu
gateway``), the count in ``stats()``, and the task back at work after the back-off
(the requests answered again, idle connections closed again); the other bus
answers meanwhile."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import pytest
from cli_helpers import ROOT, env
from waiting import wait_for

from pyrtu import pdu
from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.devices import weg as weg_map
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.reconnect import Backoff
from pyrtu.drivers.supervise import TaskFailure
from pyrtu.gateway import Gateway, GatewayLimits
from pyrtu.tcp import AsyncTcpClient

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200
PATIENCE = 30.0
#: the restarts here: 0.1 s doubling to 0.4 s
BACKOFF = Backoff(0.1, 0.4)
#: the CV100's first register, as its simulator holds it
CV_ADDRESS = 0x3300


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def error_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


@asynccontextmanager
async def served(
    limits: GatewayLimits, reports: list[TaskFailure]
) -> AsyncIterator[tuple[Gateway, str, CFW701Simulator, CV100Simulator]]:
    """A gateway on two virtual buses: a CFW701 at unit 1 on bus 0, a CV100 at
    unit 5 on bus 1."""
    with (
        vbus.VirtualBus(2, baudrate=BAUD, parity="N") as va,
        vbus.VirtualBus(2, baudrate=BAUD, parity="N") as vb,
    ):
        weg, cv = CFW701Simulator(), CV100Simulator()
        weg.serve(va.paths[1], 1, baudrate=BAUD, parity="N")
        cv.serve(vb.paths[1], 5, baudrate=BAUD, parity="N")
        try:
            async with (
                AsyncMaster(va.paths[0], BAUD, "N", timeout=0.5, retries=1) as ma,
                AsyncMaster(vb.paths[0], BAUD, "N", timeout=0.5, retries=1) as mb,
            ):
                gw = Gateway([(ma, [1]), (mb, [5])], limits, on_task=reports.append)
                await gw.start("127.0.0.1", 0)
                assert gw.address is not None
                try:
                    yield gw, "tcp://{}:{}".format(*gw.address), weg, cv
                finally:
                    await gw.close()
        finally:
            weg.close()
            cv.close()


async def read1(client: AsyncTcpClient, unit: int, address: int) -> int:
    answer = await client.request(unit, pdu.read_request(3, address, 1))
    (value,) = pdu.parse_registers(answer or b"", 1)
    return value


def failing_once(real: Callable[..., Any], error: BaseException) -> Callable[..., Any]:
    calls = [0]

    def patched(*args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        if calls[0] == 1:
            raise error
        return real(*args, **kwargs)

    return patched


def test_a_bus_worker_that_raises_is_reported_counted_and_restarted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Bus 0's worker raises on taking its next request: the request waits in the
    queue and is answered, rightly, once the worker is back; bus 1 answers meanwhile."""
    reports: list[TaskFailure] = []

    async def main() -> tuple[int, int, int, int, dict[str, object]]:
        async with served(GatewayLimits(backoff=BACKOFF), reports) as (gw, url, weg, cv):
            client = await AsyncTcpClient.connect(url, timeout=PATIENCE)
            try:
                queue = gw._buses[0].queue
                queue.pop = failing_once(queue.pop, KeyError("injected"))  # type: ignore[method-assign]
                first = asyncio.ensure_future(read1(client, 1, weg_map.P_STATUS))
                await until(lambda: bool(reports), "the failure reported")
                other = await read1(client, 5, CV_ADDRESS)  # the other bus serves on
                value = await asyncio.wait_for(first, PATIENCE)
                again = await read1(client, 1, weg_map.P_STATUS)
            finally:
                await client.close()
            expected = weg.store.holding_registers.get(weg_map.P_STATUS)
            assert other == cv.store.holding_registers.get(CV_ADDRESS)
            return value, again, expected, other, gw.stats()

    with caplog.at_level(logging.INFO, logger="pyrtu.gateway"):
        value, again, expected, _other, stats = asyncio.run(main())
    assert value == again == expected
    (report,) = reports
    assert report.task == "pyrtu-gateway-bus-0" and report.cause == "KeyError: 'injected'"
    assert 0 < report.retry_in <= 0.1 * 1.1
    assert stats["task_failures"] == 1 and stats["bus_failures"] == 0
    (line,) = error_lines(caplog)
    assert "task pyrtu-gateway-bus-0" in line and "KeyError: 'injected'" in line
    assert "restarting in" in line


def test_the_request_a_failing_worker_was_serving_is_answered_0x0B(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The worker raises while it handles a bus's error (unit 2: no drive answers);
    that request gets exception 0x0B at once, not silence, and the next is served."""
    reports: list[TaskFailure] = []

    async def main() -> tuple[bytes | None, int, int, dict[str, object]]:
        async with served(GatewayLimits(backoff=BACKOFF), reports) as (gw, url, weg, _cv):
            gw.routes = type(gw.routes)([{1: 1, 2: 2}, [5]])
            gw._failed = failing_once(gw._failed, AssertionError("injected"))  # type: ignore[method-assign]
            client = await AsyncTcpClient.connect(url, timeout=PATIENCE)
            try:
                answer = await client.exchange(2, pdu.read_request(3, 0, 1))
                value = await read1(client, 1, weg_map.P_STATUS)
            finally:
                await client.close()
            expected = weg.store.holding_registers.get(weg_map.P_STATUS)
            return answer, value, expected, gw.stats()

    with caplog.at_level(logging.INFO, logger="pyrtu.gateway"):
        answer, value, expected, stats = asyncio.run(main())
    assert answer == bytes([0x83, 0x0B])  # [AP] 7: gateway target device failed to respond
    assert value == expected
    assert stats["task_failures"] == 1 and len(reports) == 1
    assert reports[0].cause == "AssertionError: injected"


def test_the_sweeper_that_raises_is_reported_counted_and_restarted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The sweeper fails once; back after the back-off, it closes an idle connection."""
    reports: list[TaskFailure] = []
    limits = GatewayLimits(backoff=BACKOFF, idle_timeout=0.3)

    async def main() -> dict[str, object]:
        async with served(limits, reports) as (gw, _url, _weg, _cv):
            gw._sweep = failing_once(gw._sweep, OSError(5, "injected"))  # type: ignore[method-assign]
            await until(lambda: bool(reports), "the failure reported")
            host, port = gw.address or ("", 0)
            reader, writer = await asyncio.open_connection(host, port)
            try:  # an idle connection: closed by the sweeper, so it is back at work
                assert await asyncio.wait_for(reader.read(1), PATIENCE) == b""
            finally:
                writer.close()
            return gw.stats()

    with caplog.at_level(logging.INFO, logger="pyrtu.gateway"):
        stats = asyncio.run(main())
    (report,) = reports
    assert report.task == "pyrtu-gateway-sweeper"
    assert report.cause == "OSError: [Errno 5] injected"
    assert stats["task_failures"] == 1 and stats["idle_timeouts"] == 1
    (line,) = error_lines(caplog)
    assert "task pyrtu-gateway-sweeper failed: OSError: [Errno 5] injected" in line


#: ``pyrtu gateway`` with a bus queue's first pop raising (the patch, then the CLI)
WRAPPER = """\
import sys
from pyrtu.gateway._plan import FairQueue
real, calls = FairQueue.pop, [0]
def pop(self):
    calls[0] += 1
    if calls[0] == 1:
        raise KeyError("injected")
    return real(self)
FairQueue.pop = pop
from pyrtu.cli import main
sys.exit(main(sys.argv[1:]))
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


@pytest.mark.parametrize("as_json", [True, False])
def test_the_gateway_command_shows_a_failed_task_and_serves_on(as_json: bool) -> None:
    with vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        weg = CFW701Simulator()
        weg.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        try:
            port = free_port()
            args = ["gateway", "--port", f"{bus.paths[0]}", "--baudrate", str(BAUD), "--parity",
                    "N", "--listen", f"127.0.0.1:{port}", "--duration", "4"]  # fmt: skip
            proc = subprocess.Popen(
                [sys.executable, "-c", WRAPPER, *args, *(["--json"] if as_json else [])],
                cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip

            async def ask() -> int:
                give_up = time.monotonic() + PATIENCE
                while True:
                    try:
                        url = f"tcp://127.0.0.1:{port}"
                        client = await AsyncTcpClient.connect(url, timeout=10.0)
                        break
                    except OSError:
                        assert proc.poll() is None, proc.communicate()
                        assert time.monotonic() < give_up, "the gateway never listened"
                        await asyncio.sleep(0.1)
                try:
                    return await read1(client, 1, weg_map.P_STATUS)
                finally:
                    await client.close()

            value = asyncio.run(ask())
            expected = weg.store.holding_registers.get(weg_map.P_STATUS)
            out, err = proc.communicate(timeout=60)
        finally:
            weg.close()
    assert value == expected
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    if as_json:
        docs = [json.loads(line) for line in out.splitlines()]
        (event,) = [d for d in docs if d["type"] == "task_failed"]
        assert event["task"] == "pyrtu-gateway-bus-0"
        assert event["error"] == "KeyError: 'injected'" and event["retry_in"] > 0
        assert docs[-1]["type"] == "stopped" and docs[-1]["task_failures"] == 1
    else:
        (line,) = [ln for ln in err.splitlines() if "failed" in ln and "task" in ln]
        assert line.startswith(
            "pyrtu gateway: task pyrtu-gateway-bus-0 failed: KeyError: 'injected' (restarting in "
        ), err
        assert "; 1 task failures" in err
