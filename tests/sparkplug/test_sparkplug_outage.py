"""The broker SIGKILLed and started again, the primary host online throughout (it
connects again and says so): every value the drive produced reaches the host once,
live or historical, in order per metric (issue 33's target; bench/bench_sparkplug.py
measures it over a 30 s outage).  DDATA is QoS 0: a record counts as delivered
once the broker has confirmed it (pyrtu/sparkplug/node.py), so what was written to
a broker that never read it is published again after the next births."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")
pytest.importorskip("pyrtu.vbus")

from outage import WATCHED, Feeder, OutageRig, aliases, outage_rig, received, tally, wait_delivered


def run_outage(rig: OutageRig, stall: float, outage: float) -> dict[str, dict[str, int]]:
    """Values change; the broker stops reading for ``stall`` s (SIGSTOP: what the
    node writes meanwhile waits in the sockets), is SIGKILLed, stays down
    ``outage`` s and starts again; values go on changing, then the tally."""
    feeder = Feeder(rig.sim)
    feeder.start()
    try:
        time.sleep(1.0)
        proc = rig.broker.proc
        assert proc is not None
        if stall:
            os.kill(proc.pid, signal.SIGSTOP)
            time.sleep(stall)
        rig.broker.kill()
        time.sleep(outage)
        births = len(rig.host.of("DBIRTH", "weg"))
        rig.broker.start()
        rig.host.wait(lambda: len(rig.host.of("DBIRTH", "weg")) > births, "births again")
        time.sleep(1.0)
    finally:
        feeder.stop()
    wait_delivered(rig, feeder)
    time.sleep(0.5)  # anything published twice arrives meanwhile
    al = aliases(rig.host)
    return {
        name: tally(feeder.produced[name], received(rig.host, al[name], dt))
        for name, _reg, dt in WATCHED
    }


@pytest.mark.parametrize("stall", [0.0, 1.0], ids=["killed", "hung-then-killed"])
def test_broker_killed_no_value_lost_order_kept_repeats_only_historical(
    tmp_path: Path, stall: float
) -> None:
    """Killed at once, or after a second of not reading (the values written to it
    then were never read): 0 lost, 0 out of order, for each metric.  A value goes
    twice only as the historical copy of a record the broker forwarded in the
    instant before it died, before it confirmed it (QoS 0 DDATA over a broker that
    dies: at least once, never exactly once); never as a second live one."""
    with outage_rig(tmp_path) as rig:
        result = run_outage(rig, stall, 2.0)
        deaths = len(rig.host.of("DDEATH", "weg"))  # a reason for a live repeat
    for name, t in result.items():
        assert t["produced"] >= 10, (name, t)
        assert (t["lost"], t["twice_live"], t["out_of_order"]) == (0, 0, 0), (name, t, deaths)
        assert t["historical"] > 0, (name, t)  # what was read while the broker was down
