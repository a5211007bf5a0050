"""Ports come back: a poller's serial port unplugged (the virtual bus's drop) or its
TCP server refusing, going away and coming back is reported once (a `PortState`
event and one log line), retried with back-off and reopened, while the other bus
polls on and the slaves are not blamed; `stop` returns whatever the port does."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import pytest
from peers.tools import free_tcp_port
from waiting import wait_for

from pyrtu.cli._simulate_tcp import tcp_only_slave
from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.pdu.errors import PortError
from pyrtu.poller import (
    Bus,
    Point,
    Poller,
    PortState,
    SlaveState,
    Update,
    make_config,
    profile_points,
)
from pyrtu.poller.events import Event
from pyrtu.tcp.server import TcpServer

vbus = pytest.importorskip("pyrtu.vbus")
VirtualBus = vbus.VirtualBus

BAUD = 115200
#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0
#: the retry schedule of the buses here (seconds): 0.1 doubling to 0.4
HEALTH: dict[str, object] = dict(offline_after=2, backoff=0.1, max_backoff=0.4)


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def values(events: list[Event], bus: str, start: int = 0) -> int:
    return sum(1 for e in events[start:] if isinstance(e, Update) and e.point.bus == bus)


def ports(events: list[Event], bus: str) -> list[PortState]:
    return [e for e in events if isinstance(e, PortState) and e.bus == bus]


@pytest.mark.wall_clock
@pytest.mark.parametrize("master", ["aio", "thread"])
def test_an_unplugged_port_is_reported_once_and_reopened(
    master: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Bus "a" loses its own drop (the poller's adapter pulled out) and gets it back;
    bus "b" polls on meanwhile at the rate it had."""

    async def main() -> tuple[list[Event], float, float, dict[str, object]]:
        with (
            VirtualBus(2, baudrate=BAUD, parity="N") as va,
            VirtualBus(2, baudrate=BAUD, parity="N") as vb,
        ):
            weg, cv = CFW701Simulator(), CV100Simulator()
            weg.serve(va.paths[1], 1, baudrate=BAUD, parity="N")
            cv.serve(vb.paths[1], 5, baudrate=BAUD, parity="N")
            try:
                # a timeout far above the answers' few ms: a loaded VM is no outage
                options = {"baudrate": BAUD, "parity": "N", "timeout": 0.5}
                buses = [Bus("a", va.paths[0], options, **HEALTH),  # type: ignore[arg-type]
                         Bus("b", vb.paths[0], options, **HEALTH)]  # type: ignore[arg-type]  # fmt: skip
                points = profile_points("cfw701", "weg", "a", 1, 0.05)
                points += profile_points("cv100", "cv", "b", 5, 0.05)
                poller = Poller(make_config(buses, points), master=master, changes_only=False)
                events: list[Event] = []
                poller.on_event(events.append)
                async with poller:
                    await until(lambda: values(events, "a") >= 20, "bus a's values")
                    # bus b's pace with both buses up: the time its next 60 values take
                    mark, t0 = len(events), time.monotonic()
                    await until(lambda: values(events, "b", mark) >= 60, "bus b's values")
                    before = time.monotonic() - t0
                    va.unplug(0)
                    await until(lambda: len(ports(events, "a")) == 1, "bus a down")
                    # the same with bus a down (its port retried meanwhile)
                    mark, t0 = len(events), time.monotonic()
                    await until(lambda: values(events, "b", mark) >= 60, "bus b's values")
                    during = time.monotonic() - t0
                    assert values(events, "a", mark) == 0
                    assert poller.port_state("a") == "down"
                    await asyncio.sleep(0.5)  # several attempts (0.1, 0.2, 0.4 s apart)
                    with pytest.raises(PortError, match="the port is down"):
                        await poller.read("weg.status")  # fails at once, does not hang
                    va.replug(0)
                    await until(lambda: len(ports(events, "a")) == 2, "bus a up again")
                    back = len(events)
                    await until(lambda: values(events, "a", back) >= 20, "bus a's values again")
                    return events, before, during, poller.summary()
            finally:
                weg.close()
                cv.close()

    with caplog.at_level(logging.INFO, logger="pyrtu.poller"):
        events, before, during, summary = asyncio.run(main())
    down, up = ports(events, "a")
    assert (down.up, up.up) == (False, True) and down.port == up.port
    assert up.attempts >= 3 and up.since == down.since and up.time > down.time
    assert ports(events, "b") == []
    # one log line for the outage and one for its end, however many attempts failed
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("bus a: port")]
    assert len(lines) == 2 and "down" in lines[0] and "back after" in lines[1], lines
    # the port vanished, not the slave: no timeouts counted, never marked offline
    states = [(e.bus, e.slave, e.online) for e in events if isinstance(e, SlaveState)]
    assert states == [("a", 1, True), ("b", 5, True)], summary["slaves"]
    slaves = {s["bus"]: s for s in summary["slaves"]}  # type: ignore[attr-defined]
    assert slaves["a"]["timeouts"] == slaves["b"]["timeouts"] == 0
    assert slaves["a"]["state"] == "online"
    buses = {b["bus"]: b for b in summary["buses"]}  # type: ignore[attr-defined]
    assert buses["a"]["port_state"] == "up" and buses["a"]["outages"] == 1
    assert buses["b"]["outages"] == 0
    # bus b's pace is the same whether bus a is up or down (bounds: 3x and 1 s, for
    # a loaded VM; a bus held up by the other's reopening would take the back-off)
    assert during < 3 * before + 1.0, (before, during)


@pytest.mark.wall_clock
def test_a_tcp_server_refusing_then_there_then_gone_then_back() -> None:
    """A ``tcp://`` bus whose server is not up at start, comes, goes and comes back."""
    port = free_tcp_port()
    url = f"tcp://127.0.0.1:{port}"

    async def serve() -> TcpServer:
        return await TcpServer(tcp_only_slave(CFW701Simulator(), 1)).start("127.0.0.1", port)

    async def main() -> tuple[list[Event], dict[str, object]]:
        bus = Bus("net", url, {"timeout": 0.2}, **HEALTH)  # type: ignore[arg-type]
        poller = Poller(make_config([bus], profile_points("cfw701", "weg", "net", 1, 0.05)),
                        changes_only=False)  # fmt: skip
        events: list[Event] = []
        poller.on_event(events.append)
        async with poller:
            await until(lambda: len(ports(events, "net")) == 1, "the refusal")
            assert poller.port_state("net") == "down"
            await asyncio.sleep(0.5)  # attempts that fail again: not reported again
            assert len(ports(events, "net")) == 1
            server = await serve()
            await until(lambda: len(ports(events, "net")) == 2, "connected")
            mark = len(events)
            await until(lambda: values(events, "net", mark) >= 10, "values")
            await server.close()
            await until(lambda: len(ports(events, "net")) == 3, "the connection lost")
            await asyncio.sleep(0.5)
            server = await serve()
            try:
                await until(lambda: len(ports(events, "net")) == 4, "connected again")
                mark = len(events)
                await until(lambda: values(events, "net", mark) >= 10, "values again")
                # (what came so far: the server's close below may be heard before the
                # poller stops, the mux's collections read the connection's end at once)
                return list(events), poller.summary()
            finally:
                await server.close()

    events, summary = asyncio.run(main())
    states = ports(events, "net")
    assert [s.up for s in states] == [False, True, False, True]
    assert "cannot connect" in states[0].error and states[1].attempts >= 2
    assert all(s.port == url for s in states)
    (slave,) = summary["slaves"]  # type: ignore[misc]
    assert slave["timeouts"] == 0 and slave["state"] == "online"
    assert [(e.slave, e.online) for e in events if isinstance(e, SlaveState)] == [(1, True)]


@pytest.mark.wall_clock
@pytest.mark.parametrize("master", ["auto", "aio", "thread"])
def test_stop_returns_with_a_refusing_port(master: str) -> None:
    """`stop` and `PollerThread.stop` return within about a timeout, however the
    refused connections and the stop fall (durations on the interval's beat)."""
    url = f"tcp://127.0.0.1:{free_tcp_port()}"
    point = Point("x", "t", 1, "holding", 0, interval=1.0)

    async def run(duration: float) -> float:
        poller = Poller(make_config([Bus("t", url, {})], [point]), master=master)
        await poller.start()
        await asyncio.sleep(duration)
        t0 = time.monotonic()
        await asyncio.wait_for(poller.stop(), PATIENCE)
        return time.monotonic() - t0

    timeout = 1.0  # the default timeout of the bus
    for duration in (1.0, 2.0):
        assert asyncio.run(run(duration)) < timeout + 1.0
    poller = Poller(make_config([Bus("t", url, {})], [point]), master=master)
    seen: list[Event] = []
    poller.on_event(seen.append)
    thread = poller.running().start()  # a port that fails is no error: it is retried
    time.sleep(1.0)
    t0 = time.monotonic()
    thread.stop()
    assert time.monotonic() - t0 < timeout + 1.0
    assert [type(e) for e in seen] == [PortState] and not seen[0].up  # type: ignore[union-attr]
