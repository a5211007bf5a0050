"""The short soak run (bench/soak.py --short) that CI runs: the poller, the gateway and
simulated drives on the virtual bus under seeded bit errors, unplug/replug of every
kind of port, long and short requests and abusive TCP clients: every fault recovers,
no value is wrong, every process lives to the end and exits 0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: A drop is down 1 s.  The port's back-off retries after 0.5, 1 and 2 s, so the port
#: is open again within 2 s of the replug; a slave the poller took offline meanwhile is
#: probed after its own back-off (0.5 s doubling, a few probes in): 8 s bounds both
#: with room for a loaded machine.
RECOVERY_BOUND_S = 8.0


@pytest.mark.wall_clock
def test_the_short_soak_recovers_every_fault_and_reads_no_wrong_value(tmp_path: Path) -> None:
    report = tmp_path / "soak.json"
    run = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "soak.py"), "--short", "--json", str(report)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert report.exists(), run.stderr[-3000:]
    r = json.loads(report.read_text())["19200"]
    assert r["faults_injected"] >= 10
    kinds = set(r["recovery_s"])
    assert kinds == {"drive", "poller", "gateway", "gwdrive"}, r
    assert r["unrecovered"] == [], r
    assert r["slowest_recovery_s"] < RECOVERY_BOUND_S, r
    assert r["wrong_values"] == 0, r["wrong_examples"]
    assert all(r["all_alive_at_end"].values()), r["all_alive_at_end"]
    assert set(r["exit_codes"].values()) == {0}, (r["exit_codes"], r["slaves_offline_at_stop"])
    assert r["poller_updates"] > 0 and r["gateway_answers"] > 0
    # each outage reported once, and its end once: the poller's own port (a "port"
    # event each way) and the gateway's bus
    assert r["events"].get("port") == 2 * r["recovery_s"]["poller"]["n"], r["events"]
    assert r["events"].get("gateway bus down") == r["recovery_s"]["gateway"]["n"], r["events"]
    assert r["events"].get("gateway bus up") == r["recovery_s"]["gateway"]["n"], r["events"]
    assert r["good_client_errors"] == 0, r["good_client_error_examples"]
    assert r["abusers_closed_by_gateway"] > 0 and r["good_client_refused"] == 0
    assert run.returncode == 0, run.stderr[-3000:]
