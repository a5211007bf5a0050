"""Every bus task of the poller is supervised: the task is made to raise (its
scheduler's ``on_response`` patched to fail: the fault is the point) on a real
virtual bus with a simulated drive, and what the user sees is checked: one log
line naming the task and the cause, one `TaskFailed` event (a ``task_failed``
line of ``pyrtu poll --config --json``, a message on stderr without it), the
count in the bus's summary, values of that bus coming again after the back-off,
and the other bus polling on meanwhile."""

from __future__ import annotations

import asyncio
import logging
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_helpers import ROOT, env, poll_weg
from waiting import wait_for

from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.devices import weg as weg_map
from pyrtu.poller import Bus, Poller, TaskFailed, Update, make_config, profile_points
from pyrtu.poller.events import Event

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200
#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0
#: the retry schedule of the buses here (seconds): 0.1 doubling to 0.4
HEALTH: dict[str, Any] = dict(offline_after=2, backoff=0.1, max_backoff=0.4)


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def values(events: list[Event], bus: str, start: int = 0) -> int:
    return sum(1 for e in events[start:] if isinstance(e, Update) and e.point.bus == bus)


def failures(events: list[Event]) -> list[TaskFailed]:
    return [e for e in events if isinstance(e, TaskFailed)]


def failing(real: Callable[..., Any], times: int) -> tuple[Callable[..., Any], list[int]]:
    """``real``, except that its calls after the 3rd raise, ``times`` of them."""
    calls = [0]

    def patched(*args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        if 3 < calls[0] <= 3 + times:
            raise RuntimeError("injected")
        return real(*args, **kwargs)

    return patched, calls


@pytest.mark.parametrize("times", [1, 3])
def test_a_bus_task_that_raises_is_reported_counted_and_restarted(
    caplog: pytest.LogCaptureFixture, times: int
) -> None:
    """Failing ``times`` times in a row: one log line, one event (a run of failures
    is one outage, as on the shared back-off), each failure counted, then bus "a"
    polls again; bus "b" polls on all along."""

    async def main() -> tuple[list[Event], int, dict[str, Any]]:
        with (
            vbus.VirtualBus(2, baudrate=BAUD, parity="N") as va,
            vbus.VirtualBus(2, baudrate=BAUD, parity="N") as vb,
        ):
            weg, cv = CFW701Simulator(), CV100Simulator()
            weg.serve(va.paths[1], 1, baudrate=BAUD, parity="N")
            cv.serve(vb.paths[1], 5, baudrate=BAUD, parity="N")
            try:
                options = {"baudrate": BAUD, "parity": "N", "timeout": 0.5}
                buses = [Bus("a", va.paths[0], options, **HEALTH),
                         Bus("b", vb.paths[0], options, **HEALTH)]  # fmt: skip
                points = profile_points("cfw701", "weg", "a", 1, 0.05)
                points += profile_points("cv100", "cv", "b", 5, 0.05)
                poller = Poller(make_config(buses, points), changes_only=False)
                sched = poller.scheduler("a")
                sched.on_response, calls = failing(sched.on_response, times)  # type: ignore[method-assign]
                events: list[Event] = []
                poller.on_event(events.append)
                async with poller:
                    await until(lambda: bool(failures(events)), "the failure reported")
                    mark = len(events)
                    await until(lambda: values(events, "b", mark) >= 20, "bus b's values")
                    await until(lambda: calls[0] > 3 + times, "bus a's task restarted")
                    back = len(events)
                    await until(lambda: values(events, "a", back) >= 20, "bus a's values again")
                    return events, mark, poller.summary()
            finally:
                weg.close()
                cv.close()

    with caplog.at_level(logging.INFO, logger="pyrtu.poller"):
        events, _mark, summary = asyncio.run(main())
    (failure,) = failures(events)
    assert (failure.bus, failure.task) == ("a", "pyrtu-poll-a")
    assert failure.error == "RuntimeError: injected" and 0 < failure.retry_in <= 0.4 * 1.1
    assert failure.as_dict()["event"] == "task_failed"
    buses = {b["bus"]: b for b in summary["buses"]}
    assert buses["a"]["task_failures"] == times and buses["b"]["task_failures"] == 0
    # the fault was the poller's: not counted against the port or the slave
    assert buses["a"]["outages"] == 0 and buses["a"]["port_state"] == "up"
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    (line,) = [m for m in lines if "task pyrtu-poll-a failed" in m]
    assert "RuntimeError: injected" in line and "restarting in" in line
    assert lines == [line], lines  # nothing else went wrong


def test_a_read_waiting_on_the_failed_transaction_gets_the_error() -> None:
    """The transaction a failing task was in is not left hanging: the read asked
    through it fails with the task's error, the next one is answered."""

    async def main() -> tuple[str, object, object, int]:
        with vbus.VirtualBus(2, baudrate=BAUD, parity="N") as va:
            weg = CFW701Simulator()
            weg.serve(va.paths[1], 1, baudrate=BAUD, parity="N")
            try:
                options = {"baudrate": BAUD, "parity": "N", "timeout": 0.5}
                points = profile_points("cfw701", "weg", "a", 1, 60.0)
                poller = Poller(make_config([Bus("a", va.paths[0], options, **HEALTH)], points))
                sched = poller.scheduler("a")
                real = sched.on_response

                def on_response(req: Any, data: Any, now: float) -> list[Event]:
                    if req.tag and not on_response.failed:  # type: ignore[attr-defined]
                        on_response.failed = True  # type: ignore[attr-defined]
                        raise RuntimeError("injected")
                    return real(req, data, now)

                on_response.failed = False  # type: ignore[attr-defined]
                sched.on_response = on_response  # type: ignore[method-assign]
                async with poller:
                    with pytest.raises(RuntimeError, match="injected") as first:
                        await asyncio.wait_for(poller.read("weg.status"), PATIENCE)
                    value = await asyncio.wait_for(poller.read("weg.status"), PATIENCE)
                    count = poller.summary()["buses"][0]["task_failures"]
                    # the drive's own status register (the peer's side of the wire)
                    expected = weg.store.holding_registers.get(weg_map.P_STATUS)
                    return str(first.value), value, expected, count
            finally:
                weg.close()

    error, value, expected, count = asyncio.run(main())
    assert error == "injected" and count == 1
    assert value == expected


#: ``pyrtu poll`` with the scheduler's 4th answer raising (the patch, then the CLI)
WRAPPER = """\
import sys
from pyrtu.poller.schedule import BusScheduler
real, calls = BusScheduler.on_response, [0]
def on_response(self, *args):
    calls[0] += 1
    if calls[0] == 4:
        raise RuntimeError("injected")
    return real(self, *args)
BusScheduler.on_response = on_response
from pyrtu.cli import main
sys.exit(main(sys.argv[1:]))
"""

CONFIG = poll_weg(timeout=0.5)


@pytest.mark.parametrize("json", [True, False])
def test_the_poll_command_shows_a_failed_bus_task_and_goes_on(tmp_path: Path, json: bool) -> None:
    with vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        weg = CFW701Simulator()
        weg.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        try:
            cfg = tmp_path / "points.toml"
            cfg.write_text(CONFIG.format(port=bus.paths[0]))
            args = ["poll", "--config", str(cfg), "--duration", "2", "--all"]
            proc = subprocess.run(
                [sys.executable, "-c", WRAPPER, *args, *(["--json"] if json else [])],
                cwd=ROOT, env=env(), capture_output=True, text=True, timeout=60,
            )  # fmt: skip
        finally:
            weg.close()
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    if json:
        import json as json_module

        docs = [json_module.loads(line) for line in proc.stdout.splitlines()]
        (event,) = [d for d in docs if d.get("event") == "task_failed"]
        assert event["bus"] == "line1" and event["task"] == "pyrtu-poll-line1"
        assert event["error"] == "RuntimeError: injected" and event["retry_in"] > 0
        at = docs.index(event)
        assert any("point" in d and "event" not in d for d in docs[at:]), "no value after it"
        assert docs[-1]["buses"][0]["task_failures"] == 1
    else:
        (line,) = [ln for ln in proc.stderr.splitlines() if "failed" in ln]
        assert line.startswith(
            "pyrtu poll: bus line1: task pyrtu-poll-line1 failed: RuntimeError: injected "
            "(restarting in "
        ), proc.stderr
        at = proc.stdout.index("weg.status")  # values before and after it
        assert proc.stdout.count("weg.status") >= 10, proc.stdout[at:]
        assert "1 task failures" in proc.stdout
