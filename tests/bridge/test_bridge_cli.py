"""``pyrtu bridge`` as a user runs it: SIGTERM drains and exits 0 with the edge
``offline``; refused credentials exit 3 naming the broker and the user (never the
password); ``--json`` gives events and stats; a closed pipe ends it quietly; the
bridge killed with SIGKILL and started again goes on with the next sequence
numbers (none reused, none lost that was accepted before the last fsync)."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from bridge_configs import weg_on_line
from cli_helpers import kill_after_each_test
from mqtt_broker import Broker, Client

from pyrtu.devices import CFW701Simulator

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200


@contextlib.contextmanager
def drive() -> Iterator[Any]:
    with vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        try:
            yield bus
        finally:
            sim.close()


def write_config(tmp: Path, url: str, port: str, mqtt: str = "") -> Path:
    f = tmp / "bridge.toml"
    f.write_text(f"""
[mqtt]
url = "{url}"
edge = "cli"
stats_interval = 0.2
{mqtt}
{weg_on_line(port, 0.02)}""")
    return f


STARTED: list[subprocess.Popen[str]] = []
_no_bridge_left = kill_after_each_test(STARTED)


def start(*args: str) -> subprocess.Popen[str]:
    p = _popen(*args)
    STARTED.append(p)
    return p


def _popen(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "bridge", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def first_lines(p: subprocess.Popen[str], n: int) -> list[dict[str, Any]]:
    assert p.stdout is not None
    out = []
    for _ in range(n):
        line = p.stdout.readline()
        assert line, p.stderr.read() if p.stderr else ""
        out.append(json.loads(line))
    return out


def test_sigterm_drains_and_exits_0(tmp_path: Path) -> None:
    with Broker(tmp_path) as broker, drive() as bus, Client(broker, ["pyrtu/cli/#"]) as sub:
        cfg = write_config(tmp_path, broker.url, bus.paths[0])
        p = start("--config", str(cfg), "--json")
        events = first_lines(p, 3)
        assert "broker_up" in [e["event"] for e in events]
        sub.wait(lambda: bool(sub.on("pyrtu/cli/line/1/weg.status")), "a value")
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=30)
        assert p.returncode == 0, err
        lines = [json.loads(x) for x in out.splitlines()]
        end = lines[-1]
        assert end["event"] == "end" and end["outbox_depth"] == 0 and end["drops"] == 0
        stats = [x for x in events + lines if x["event"] == "stats"]
        assert stats and {"outbox_depth", "publish_latency_p50_ms", "drops"} <= set(stats[0])
        sub.wait(lambda: sub.on("pyrtu/cli/status")[-1:] == [b"offline"], "offline")
        assert sub.on("pyrtu/cli/stats")
        assert "Traceback" not in err


def test_refused_credentials_exit_3(tmp_path: Path) -> None:
    with Broker(tmp_path, users={"edge": "good"}) as broker, drive() as bus:
        (tmp_path / "pw").write_text("not-the-password\n")
        cfg = write_config(
            tmp_path, broker.url, bus.paths[0], 'username = "edge"\npassword_file = "pw"'
        )
        p = start("--config", str(cfg))
        out, err = p.communicate(timeout=60)
        assert p.returncode == 3, err
        assert f"127.0.0.1:{broker.port}" in err and "'edge'" in err
        assert "not-the-password" not in err + out and "Traceback" not in err


def test_a_closed_pipe_ends_it_quietly(tmp_path: Path) -> None:
    with Broker(tmp_path) as broker, drive() as bus:
        cfg = write_config(tmp_path, broker.url, bus.paths[0])
        cmd = f"{sys.executable} -m pyrtu bridge --config {cfg} --json | head -1"
        r = subprocess.run(
            ["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["event"] in ("broker_up", "slave")
        assert "Traceback" not in r.stderr


def test_sigkill_and_restart_continue_the_sequence(tmp_path: Path) -> None:
    """fsync_interval 0: every record durable at once; after SIGKILL the restarted
    bridge publishes what was not acknowledged with the same numbers, then new ones
    (from the next reserved block): no number carries two different values, none
    from before the kill is missing."""
    with Broker(tmp_path) as broker, drive() as bus, Client(broker, ["pyrtu/cli/line/#"]) as sub:
        cfg = write_config(
            tmp_path, broker.url, bus.paths[0], "fsync_interval = 0\nmax_age = 0.001"
        )
        status = Client(broker, ["pyrtu/cli/status"])
        p = start("--config", str(cfg))
        sub.wait(lambda: len(sub.messages) > 300, "values")
        os.kill(p.pid, signal.SIGKILL)
        p.communicate(timeout=10)
        # the broker publishes the last will: the edge is offline
        status.wait(lambda: status.on("pyrtu/cli/status")[-1:] == [b"offline"], "the will")
        assert status.on("pyrtu/cli/status") == [b"online", b"offline"]
        status.close()
        mark = len(sub.messages)
        p = start("--config", str(cfg))
        sub.wait(lambda: len(sub.messages) > mark + 300, "values after the restart")
        p.send_signal(signal.SIGTERM)
        p.communicate(timeout=30)
        assert p.returncode == 0
        time.sleep(0.2)
        by_seq: dict[int, bytes] = {}
        for t, body, *_ in list(sub.messages):
            if t.endswith("/status"):
                continue
            doc = json.loads(body)
            seq = doc.pop("seq")
            doc.pop("historical", None)
            key = (t + json.dumps(doc, sort_keys=True)).encode()
            assert by_seq.setdefault(seq, key) == key, f"seq {seq} carried two values"
        got = sorted(by_seq)
        # numbers are never reused: the restarted outbox skips the block it had
        # reserved, so there is exactly one gap, at the restart, and none before it
        gaps = [(a, b) for a, b in itertools.pairwise(got) if b != a + 1]
        assert len(gaps) == 1, gaps[:5]
        first_after = gaps[0][1]
        assert all(by_seq[n] for n in range(got[0], gaps[0][0] + 1))
        assert min(s for s in got if s >= first_after) == first_after


def test_a_broker_never_reached_ends_with_exit_3_and_keeps_the_backlog(tmp_path: Path) -> None:
    """No broker listens: the bridge polls into the outbox, reports the broker down
    once, and --duration ends it with exit 3 and one line saying the broker was
    never reached (issue 27.14); the next run delivers the backlog and exits 0."""
    from mqtt_broker import free_port

    with drive() as bus:
        port = free_port()
        cfg = write_config(tmp_path, f"mqtt://127.0.0.1:{port}", bus.paths[0])
        p = start("--config", str(cfg), "--json", "--duration", "1.5")
        out, err = p.communicate(timeout=60)
        assert p.returncode == 3, err
        lines = [json.loads(x) for x in out.splitlines()]
        assert [e.get("event") for e in lines].count("broker_down") == 1
        end, error = lines[-2:]
        assert end["event"] == "end" and end["outbox_depth"] > 0 and end["drops"] == 0
        assert error["ok"] is False and error["exit_code"] == 3
        assert f"broker 127.0.0.1:{port} never reached during the run" in error["message"]
        assert "refused" in error["message"].lower()
        (last,) = [x for x in err.splitlines() if "never reached" in x]
        assert last == f"pyrtu bridge: port error: {error['message']}" and "Traceback" not in err
        with Broker(tmp_path, port=port) as _broker, Client(_broker, ["pyrtu/cli/line/#"]) as sub:
            p = start("--config", str(cfg), "--duration", "3")
            backlog = end["outbox_depth"]
            sub.wait(lambda: sum(b"historical" in m[1] for m in sub.messages) >= backlog, "backlog")
            p.communicate(timeout=60)
            assert p.returncode == 0


def test_mqtts_against_a_plain_broker_says_so_and_exits_3(tmp_path: Path) -> None:
    """A real mosquitto listening plain MQTT, the bridge told mqtts://: the TLS
    handshake is broken off; the bridge says so with the hint, retries, and ends
    with exit 3 (never connected)."""
    with Broker(tmp_path) as broker, drive() as bus:
        cfg = write_config(tmp_path, f"mqtts://127.0.0.1:{broker.port}", bus.paths[0])
        p = start("--config", str(cfg), "--duration", "1.5")
        _out, err = p.communicate(timeout=60)
        assert p.returncode == 3, err
        hint = f"is it a plain MQTT broker? then use mqtt://127.0.0.1:{broker.port}"
        assert "TLS handshake failed" in err and hint in err, err
        assert "never reached during the run" in err.splitlines()[-1]
        assert "Traceback" not in err


def test_a_password_file_missing_exits_2_and_a_ca_that_cannot_be_used_exits_3(
    tmp_path: Path,
) -> None:
    with drive() as bus:
        cfg = write_config(tmp_path, "mqtt://127.0.0.1:1", bus.paths[0],
                           'username = "edge"\npassword_file = "missing.pw"')  # fmt: skip
        for args in (("--check", str(cfg)), ("--config", str(cfg))):  # the same (#27.14)
            p = start(*args)
            _out, err = p.communicate(timeout=60)
            assert p.returncode == 2, err
            assert f"mqtt: password_file: {tmp_path / 'missing.pw'}: no such file" in err
            assert "Traceback" not in err
        (tmp_path / "nope.pem").write_text("not a certificate\n")  # there, but not PEM
        cfg = write_config(tmp_path, "mqtts://127.0.0.1:1", bus.paths[0], 'ca = "nope.pem"')
        p = start("--config", str(cfg))
        _out, err = p.communicate(timeout=60)
        assert p.returncode == 3, err
        assert "nope.pem" in err and "Traceback" not in err
