"""``pyrtu poll --config``: JSON updates and the summary on the virtual bus, config
errors with exit status 2 and no traceback, the single-range form unchanged."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import pyrtu

from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.devices import weg as W

vbus = pytest.importorskip("pyrtu.vbus")

CONFIG = """\
[defaults]
bus = "line1"
interval = 0.05

[[bus]]
name = "line1"
port = "{port}"
baudrate = 115200
parity = "N"
timeout = 0.05
offline_after = 2

[[device]]
bus = "line1"
slave = 1
profile = "cfw701"
name = "weg"

[[point]]
name = "cv.status"
slave = 5
table = "holding"
address = 0x3300

[[point]]
name = "ghost.status"
slave = 9
table = "holding"
address = 0
"""


def test_json_updates_and_summary(tmp_path: Path) -> None:
    with vbus.VirtualBus(3, baudrate=115200, parity="N") as bus:
        weg, cv = CFW701Simulator(), CV100Simulator()
        weg.serve(bus.paths[1], 1, baudrate=115200, parity="N")
        cv.serve(bus.paths[2], 5, baudrate=115200, parity="N")
        try:
            cfg = tmp_path / "points.toml"
            cfg.write_text(CONFIG.format(port=bus.paths[0]))
            r = pyrtu("poll", "--config", cfg, "--duration", "3", "--json")
        finally:
            weg.close()
            cv.close()
    assert r.code == 0, r.err
    docs = r.json_lines()
    *updates, summary = docs
    assert summary["summary"] is True
    names = {u["point"] for u in updates}
    assert names == {"weg.status", "weg.speed", "weg.current", "weg.fault", "weg.alarm",
                     "cv.status"}  # fmt: skip
    for u in updates:
        assert set(u) == {"point", "value", "time", "slave", "bus"} and u["bus"] == "line1"
    status = next(u for u in updates if u["point"] == "weg.status")
    assert status["value"] == CFW701Simulator().store.holding_registers.get(W.P_STATUS)
    (b,) = summary["buses"]
    assert 0 < b["utilisation"] <= 1 and b["transactions"] > 10
    slaves = {s["slave"]: s for s in summary["slaves"]}
    assert slaves[1]["state"] == slaves[5]["state"] == "online"
    assert slaves[9]["state"] == "offline" and slaves[9]["timeouts"] >= 2
    assert slaves[9]["responses"] == 0
    assert "Traceback" not in r.err


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            '[[bus]]\nname = 1\nport = "{port}"\n',
            "points.toml:2: bus[0]: name: must be a non-empty",
        ),
        ("[[bus]]\nname = 1\n", "points.toml:1: bus[0]: port: missing"),
        (CONFIG.replace("0x3300", "-1"), 'points.toml:23: point[0] ("cv.status"): address:'),
        (CONFIG.replace("slave = 9", "slave = 300"), "slave: must be 1..247, not 300"),
        ("[[bus]\n", "points.toml: "),
    ],
)
def test_config_errors_exit_2_before_any_port_opens(
    tmp_path: Path, text: str, message: str
) -> None:
    cfg = tmp_path / "points.toml"
    # the port does not exist: a config error must be reported before opening it
    cfg.write_text(text.replace("{port}", "/nonexistent/ttyX"))
    r = pyrtu("poll", "--config", cfg, "--json")
    assert r.code == 2, (r.out, r.err)
    assert r.err.startswith("pyrtu poll: config error: ") and message in r.err
    assert "Traceback" not in r.err and "nonexistent" not in r.err and r.out == ""


def test_missing_file_and_missing_port(tmp_path: Path) -> None:
    r = pyrtu("poll", "--config", tmp_path / "none.toml")
    assert r.code == 2 and "none.toml: no such file" in r.err and "Traceback" not in r.err
    cfg = tmp_path / "points.toml"
    cfg.write_text(CONFIG.format(port="/nonexistent/ttyX"))
    r = pyrtu("-v", "poll", "--config", cfg, "--duration", "1")
    assert r.code == 3 and "/nonexistent/ttyX" in r.err and "Traceback" not in r.err
    r = pyrtu("poll", "--config", cfg, "--duration", "-1")
    assert r.code == 2 and "--duration" in r.err


def test_single_range_form_still_works() -> None:
    r = pyrtu("poll", "loop://", "0", "--count", "1", "--timeout", "0.05", "--json")
    # loop:// sends the request back: a frame error (6), reported by the old command
    assert r.code == 6 and '"final": true' in r.out
