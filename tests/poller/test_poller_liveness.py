"""Is the slave there? The poller's answer, end to end (issue 27):

* a dead slave behind a Modbus TCP gateway: the gateway answers exception 0x0B
  (gateway target device failed to respond, Application Protocol V1.1b section 7)
  in its name, and that is no answer of the slave: the poller takes it offline,
  and the bridge publishes its points ``stale`` (a real mosquitto);
* a device back after an outage longer than the old back-off's growth is found
  within about a second (the back-off stops at 1 s), on a ``tcp://`` bus (its
  connection reopened) and on a serial bus (its probes), while the bus's other
  slave keeps its rate."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
from mqtt_broker import Broker, Client

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge
from pyrtu.cli._simulate_tcp import tcp_only_slave
from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.aio import run as aio_run
from pyrtu.gateway import Gateway
from pyrtu.poller import Bus, Poller, PortState, SlaveState, Update, make_config, profile_points
from pyrtu.poller.events import Event
from pyrtu.tcp.server import TcpServer

vbus = pytest.importorskip("pyrtu.vbus")
VirtualBus = vbus.VirtualBus

BAUD = 115200
#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0
#: the back-off's cap (docs/POLLER.md, "Slave health" and "Ports"): 1 s
MAX_BACKOFF = 1.0


async def until(condition: Callable[[], bool], what: str, patience: float = PATIENCE) -> None:
    """Wait until ``condition()`` holds (checked every 10 ms); fail after ``patience``."""
    loop = asyncio.get_running_loop()
    give_up = loop.time() + patience
    while not condition():
        assert loop.time() < give_up, f"gave up waiting for {what}"
        await asyncio.sleep(0.01)


def states(events: list[Event]) -> list[tuple[int, bool]]:
    return [(e.slave, e.online) for e in events if isinstance(e, SlaveState)]


def values(events: list[Event], slave: int, start: int = 0) -> int:
    return sum(1 for e in events[start:] if isinstance(e, Update) and e.point.slave == slave)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


@contextlib.asynccontextmanager
async def gateway_to(path: str) -> AsyncIterator[str]:
    """A `Gateway` on 127.0.0.1 onto the virtual bus's drop ``path`` (unit 1, a bus
    timeout of 0.1 s); yields its ``tcp://`` URL."""
    async with AsyncMaster(path, BAUD, "N", timeout=0.1) as master:
        gateway = await Gateway([(master, [1])]).start("127.0.0.1", 0)
        try:
            assert gateway.address is not None
            yield "tcp://{}:{}".format(*gateway.address)
        finally:
            await gateway.close()


def test_the_bridge_publishes_a_dead_slave_behind_a_gateway_stale(tmp_path: Path) -> None:
    """The same through the bridge to mosquitto: the drive behind the gateway stops,
    its points are published ``stale`` and its status ``offline``."""
    topic = "pyrtu/e1/net/1/weg.speed"

    def quality(sub: Client) -> str | None:
        got = sub.on(topic)
        return json.loads(got[-1])["quality"] if got else None

    with Broker(tmp_path) as broker, VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        sub = Client(broker, ["pyrtu/#"])
        try:

            async def main() -> None:
                async with gateway_to(bus.paths[0]) as url:
                    text = (
                        f'[mqtt]\nurl = "{broker.url}"\nedge = "e1"\n'
                        f'outbox = "{tmp_path / "ob"}"\n'
                        f'[[bus]]\nname = "net"\nport = "{url}"\ntimeout = 1.0\n'
                        "offline_after = 2\n"
                        '[[device]]\nbus = "net"\nslave = 1\nprofile = "cfw701"\n'
                        'name = "weg"\ninterval = 0.05\n'
                    )
                    async with Bridge(parse_bridge_config(text, "b.toml")):
                        await until(lambda: quality(sub) == "good", "a good value")
                        sim.close()
                        await until(lambda: quality(sub) == "stale", "stale")
                        await until(
                            lambda: sub.on("pyrtu/e1/net/1/status")[-1:] == [b"offline"],
                            "offline",
                        )

            aio_run(main())
        finally:
            sub.close()
            with contextlib.suppress(Exception):
                sim.close()


def test_a_dead_slave_behind_a_gateway_goes_offline_and_comes_back() -> None:
    """A real gateway (`pyrtu.gateway.Gateway`) in front of a CFW701 simulated on the
    virtual bus; the poller reads it over ``tcp://``.  The drive stops: the gateway
    answers 0x0B after its bus timeout (0.1 s), the poller (timeout 1 s: it never
    times out itself) takes the slave offline after ``offline_after`` of them; the
    drive back, it is online again."""

    async def main() -> tuple[list[Event], dict[str, object], dict[str, object]]:
        with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
            sim = CFW701Simulator()
            sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
            try:
                async with AsyncMaster(bus.paths[0], BAUD, "N", timeout=0.1) as master:
                    gateway = await Gateway([(master, [1])]).start("127.0.0.1", 0)
                    try:
                        assert gateway.address is not None
                        url = "tcp://{}:{}".format(*gateway.address)
                        net = Bus("net", url, {"timeout": 1.0}, offline_after=2)
                        points = profile_points("cfw701", "weg", "net", 1, 0.05)
                        poller = Poller(make_config([net], points), changes_only=False)
                        events: list[Event] = []
                        poller.on_event(events.append)
                        async with poller:
                            await until(lambda: values(events, 1) >= 5, "the drive's values")
                            sim.close()  # the drive is dead; the gateway is not
                            await until(lambda: (1, False) in states(events), "offline")
                            sim = CFW701Simulator()
                            sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
                            await until(lambda: states(events)[-1] == (1, True), "back")
                            summary = poller.summary()
                        return events, summary, gateway.stats()
                    finally:
                        await gateway.close()
            finally:
                with contextlib.suppress(Exception):
                    sim.close()

    events, summary, gw = asyncio.run(main())
    assert states(events) == [(1, True), (1, False), (1, True)]
    assert not any(isinstance(e, PortState) for e in events)  # the connection held
    (slave,) = summary["slaves"]  # type: ignore[misc]
    assert slave["timeouts"] >= 2  # its 0x0B counted as no answer
    assert isinstance(gw["timeouts"], int) and gw["timeouts"] >= 2  # its 0x0B answers


@pytest.mark.wall_clock
def test_a_tcp_device_back_after_an_outage_is_read_within_a_second() -> None:
    """The device's server gone for 5 s (the old back-off, 0.5 s doubling, would wait
    until 7.5 s +-10 %), then back: fresh values within the 1 s cap, plus a connect,
    the poller's interval and a transaction."""
    port = free_port()
    url = f"tcp://127.0.0.1:{port}"

    async def serve() -> TcpServer:
        return await TcpServer(tcp_only_slave(CFW701Simulator(), 1)).start("127.0.0.1", port)

    async def main() -> float:
        server = await serve()
        net = Bus("net", url, {"timeout": 0.2})  # the default back-off
        poller = Poller(make_config([net], profile_points("cfw701", "weg", "net", 1, 0.05)),
                        changes_only=False)  # fmt: skip
        events: list[Event] = []
        poller.on_event(events.append)
        async with poller:
            await until(lambda: values(events, 1) >= 5, "values")
            await server.close()
            await until(lambda: any(isinstance(e, PortState) for e in events), "the loss")
            await asyncio.sleep(5.0)
            server = await serve()
            back = time.monotonic()
            mark = len(events)
            try:
                await until(lambda: values(events, 1, mark) >= 1, "fresh values")
                return time.monotonic() - back
            finally:
                await server.close()

    delay = asyncio.run(main())
    assert delay <= MAX_BACKOFF + 0.2 + 0.05 + 0.25, delay


@pytest.mark.wall_clock
def test_a_serial_slave_back_after_an_outage_is_found_soon_the_other_at_its_rate() -> None:
    """Two drives on the virtual bus; the CV100 (5) away for 9 s after it went
    offline (the old back-off, doubling to 30 s, would probe next at about 15.8 s),
    then back: online again within the 1 s cap (its timeout's share floor, 19 x
    ~40 ms, is below it) plus a probe; the CFW701 (1) keeps its rate meanwhile."""
    timeout = 0.03

    async def main() -> tuple[float, float, float]:
        with VirtualBus(3, baudrate=BAUD, parity="N") as bus:
            sims = [CFW701Simulator(), CV100Simulator()]
            for drop, (sim, address) in enumerate(zip(sims, (1, 5), strict=True), start=1):
                sim.serve(bus.paths[drop], address, baudrate=BAUD, parity="N")
            try:
                line = Bus("line", bus.paths[0], {"baudrate": BAUD, "parity": "N",
                                                  "timeout": timeout})  # fmt: skip
                points = profile_points("cfw701", "weg", "line", 1, 0.05)
                points += profile_points("cv100", "cv", "line", 5, 0.05)
                poller = Poller(make_config([line], points), changes_only=False)
                events: list[Event] = []
                poller.on_event(events.append)
                async with poller:
                    await until(lambda: values(events, 5) >= 10, "slave 5's values")
                    mark, t0 = len(events), time.monotonic()
                    await asyncio.sleep(2.0)
                    before = values(events, 1, mark) / (time.monotonic() - t0)
                    sims[1].close()
                    await until(lambda: (5, False) in states(events), "slave 5 offline")
                    mark, t0 = len(events), time.monotonic()
                    await asyncio.sleep(9.0)
                    during = values(events, 1, mark) / (time.monotonic() - t0)
                    sims[1] = CV100Simulator()
                    sims[1].serve(bus.paths[2], 5, baudrate=BAUD, parity="N")
                    back = time.monotonic()
                    await until(lambda: states(events)[-1] == (5, True), "slave 5 back")
                    return time.monotonic() - back, before, during
            finally:
                for sim in sims:
                    with contextlib.suppress(Exception):
                        sim.close()

    delay, before, during = asyncio.run(main())
    assert delay <= MAX_BACKOFF + timeout + 0.5, delay
    assert during >= 0.8 * before, (before, during)
