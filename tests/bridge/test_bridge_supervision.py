"""Every background task of the bridge is supervised: each is made to raise (its
coroutine patched to fail once: the fault is the point) under a running bridge
with a real mosquitto, and what the user sees is checked: one log line naming the
task and the cause, a ``task_failed`` event, the count in the stats, and the task
back at work after the shared back-off (the bridge connected again, the figures
reported again, the next command written)."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from mqtt_broker import Broker, Client
from test_bridge_broker import POINTS, drives, toml, topic
from test_bridge_writes import BASE, ref, results, rig, wait_results
from waiting import wait_for

from pyrtu.bridge import BridgeConfig, parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.drivers.aio import run as aio_run

PATIENCE = 15.0


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


@contextlib.contextmanager
def supervised(
    tmp_path: Path, topics: str = "pyrtu/e1/#", mqtt: str = ""
) -> Iterator[tuple[BridgeConfig, list[BridgeEvent], Client]]:
    """What each test runs its `Bridge` in: a mosquitto, the drives on a virtual bus,
    the bridge's configuration (``mqtt``: more lines of its [mqtt] table), the list
    the bridge's events go to (see `watched`) and a subscriber to ``topics``."""
    with Broker(tmp_path) as broker, drives() as (bus, _sims):
        cfg = parse_bridge_config(toml(broker.url, bus.paths[0], tmp_path / "ob", mqtt), "b.toml")
        with Client(broker, [topics]) as sub:
            yield cfg, [], sub


def watched(cfg: BridgeConfig, events: list[BridgeEvent]) -> Bridge:
    """A bridge whose events are appended to ``events``."""
    bridge = Bridge(cfg)
    bridge.on_event(events.append)
    return bridge


def failures(events: list[BridgeEvent]) -> list[dict[str, Any]]:
    return [e.detail for e in events if e.kind == "task_failed"]


def once(error: BaseException, then: Callable[..., Any], times: int = 1) -> Callable[..., Any]:
    """``then``, except that the first ``times`` calls raise ``error``."""
    calls = 0

    def patched(*args: Any, **kwargs: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls <= times:
            raise error
        return then(*args, **kwargs)

    return patched


def the_log_lines(caplog: pytest.LogCaptureFixture, task: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.ERROR and f"task {task} failed" in r.getMessage()
    ]


def test_the_broker_connection_task_fails_is_reported_and_restarted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pyrtu.bridge")
    with supervised(tmp_path) as (cfg, events, sub):

        async def main() -> dict[str, Any]:
            bridge = watched(cfg, events)
            # the connection task raises once it is connected, a fault of its own
            bridge._on_connected = once(RuntimeError("injected"), bridge._on_connected)  # type: ignore[method-assign]
            async with bridge:
                await until(lambda: bool(failures(events)), "the failure reported")
                # restarted: connected again, the values published
                await until(lambda: all(sub.on(topic(n)) for n in POINTS), "the values")
                await until(lambda: sub.on("pyrtu/e1/status")[-1:] == [b"online"], "online")
                return bridge.stats()

        stats = aio_run(main())
        (failure,) = failures(events)
        assert failure["task"] == "pyrtu-bridge-mqtt"
        assert failure["error"] == "RuntimeError: injected" and failure["retry_in"] >= 0
        assert stats["task_failures"] == 1 and stats["connections"] == 2
        (line,) = the_log_lines(caplog, "pyrtu-bridge-mqtt")
        assert "RuntimeError: injected" in line and "restarting in" in line


@pytest.mark.parametrize("times", [1, 3])
def test_the_stats_task_fails_is_reported_and_restarted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, times: int
) -> None:
    """Failing ``times`` times in a row: reported once (one line, one event, as
    every outage on the shared back-off), each failure counted, then back."""
    caplog.set_level(logging.INFO, logger="pyrtu.bridge")
    with supervised(tmp_path, "pyrtu/e1/stats", "stats_interval = 0.05") as (cfg, events, sub):

        async def main() -> None:
            bridge = watched(cfg, events)
            flaky = once(ZeroDivisionError("injected"), bridge.stats, times)
            bridge.stats = flaky  # type: ignore[method-assign]
            async with bridge:
                await until(lambda: bool(failures(events)), "the failure reported")
                await until(lambda: bool(sub.on("pyrtu/e1/stats")), "the stats again")

        aio_run(main())
        doc = json.loads(sub.on("pyrtu/e1/stats")[-1])
        (failure,) = failures(events)
        assert failure["task"] == "pyrtu-bridge-stats"
        assert failure["error"] == "ZeroDivisionError: injected"
        assert doc["task_failures"] == times
        (line,) = the_log_lines(caplog, "pyrtu-bridge-stats")
        assert "ZeroDivisionError: injected" in line


def test_a_writer_that_fails_answers_its_command_and_takes_the_next(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pyrtu.bridge")
    with rig(tmp_path) as (_b, sim, bridge, cl):
        events: list[BridgeEvent] = []
        bridge.on_event(events.append)
        bridge.poller.read = once(TypeError("injected"), bridge.poller.read)  # type: ignore[method-assign]
        cl.publish(f"{BASE}/weg.ref/set", b'{"value": 1111, "id": "w1"}')
        (res,) = wait_results(cl, 1)
        assert res["ok"] is False and res["id"] == "w1" and res["error"] == "failed"
        assert "TypeError: injected" in res["message"]
        # the slave is not left deaf to commands
        cl.publish(f"{BASE}/weg.ref/set", b'{"value": 2222, "id": "w2"}')
        res = wait_results(cl, 2)[1]
        assert res["ok"] is True and res["id"] == "w2" and ref(sim) == 2222
        (failure,) = failures(events)
        assert failure["task"] == "pyrtu-bridge-writes-line-1"
        assert failure["error"] == "TypeError: injected"
        assert bridge.stats()["task_failures"] == 1
        assert bridge.writer.stats()["failed"] == 1
        assert len(results(cl)) == 2
        (line,) = the_log_lines(caplog, "pyrtu-bridge-writes-line-1")
        assert "TypeError: injected" in line


def test_a_poller_bus_task_that_fails_is_a_bridge_event_and_the_values_come_again(
    tmp_path: Path,
) -> None:
    """The poller's bus task (supervised by the poller: logged and counted there) is
    reported in the bridge's events too, and the values are published again."""
    with supervised(tmp_path) as (cfg, events, sub):

        async def main() -> dict[str, Any]:
            bridge = watched(cfg, events)
            sched = bridge.poller.scheduler("line")
            sched.on_response = once(RuntimeError("injected"), sched.on_response)  # type: ignore[method-assign]
            async with bridge:
                await until(lambda: bool(failures(events)), "the failure reported")
                mark = {n: len(sub.on(topic(n))) for n in POINTS}
                await until(
                    lambda: all(len(sub.on(topic(n))) > mark[n] for n in ("weg.status",)),
                    "the values (the first read failed)",
                )
                return bridge.poller.summary()

        summary = aio_run(main())
        (failure,) = failures(events)
        assert failure["task"] == "pyrtu-poll-line" and failure["bus"] == "line"
        assert failure["error"] == "RuntimeError: injected"
        assert summary["buses"][0]["task_failures"] == 1
