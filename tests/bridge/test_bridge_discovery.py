"""Home Assistant MQTT discovery through a real mosquitto: one retained config per
point, grouped into one device per drive (model and name from the profile),
read-only points as sensors, writable ones as numbers wired to their set topics,
availability from the edge's and the slave's status; a command as Home Assistant
sends it (the number's command_template) is written to the drive."""

from __future__ import annotations

import json
from pathlib import Path

from mqtt_broker import Client
from test_bridge_writes import BASE, rig, wait_results

from pyrtu.bridge.discovery import component
from pyrtu.poller import Point


def test_discovery_configs_and_a_command_as_home_assistant_sends_it(tmp_path: Path) -> None:
    with rig(tmp_path, "discovery = true") as (broker, sim, _bridge, cl):
        with Client(broker, ["homeassistant/#"]) as ha:
            ha.wait(lambda: len(ha.messages) >= 7, "7 discovery configs")
            docs = {t: json.loads(p) for t, p, retain, *_ in ha.messages if retain}
        assert len(docs) == 7
        speed = docs["homeassistant/sensor/pyrtu_e1/line_1_weg_speed/config"]
        assert speed["state_topic"] == f"{BASE}/weg.speed"
        assert speed["name"] == "speed" and speed["value_template"] == "{{ value_json.value }}"
        assert speed["device"]["model"] == "CFW701" and speed["device"]["manufacturer"] == "WEG"
        assert speed["device"]["name"] == "weg"
        assert [a["topic"] for a in speed["availability"]] == ["pyrtu/e1/status", f"{BASE}/status"]
        assert speed["availability_mode"] == "all"
        ref = docs["homeassistant/number/pyrtu_e1/line_1_weg_ref/config"]
        assert ref["command_topic"] == f"{BASE}/weg.ref/set"
        assert (ref["min"], ref["max"], ref["step"]) == (0, 8192, 1.0)
        # one device for the drive: every config names the same identifiers
        assert len({json.dumps(d["device"]["identifiers"]) for d in docs.values()}) == 1
        # what Home Assistant publishes for a number: the rendered template, "1234.0"
        cl.publish(ref["command_topic"], b"1234.0")
        (res,) = wait_results(cl, 1)
        assert res["ok"] is True and res["value"] == 1234
        assert int(sim.store.holding_registers.get(683)) == 1234


def test_components() -> None:
    bit = Point("b", "l", 1, "coils", 0)
    word = Point("w", "l", 1, "holding", 0)
    text = Point("t", "l", 1, "holding", 0, type="string", count=4)
    assert [component(bit, False), component(bit, True)] == ["binary_sensor", "switch"]
    assert [component(word, False), component(word, True)] == ["sensor", "number"]
    assert [component(text, False), component(text, True)] == ["sensor", "text"]
    mode = Point("m", "l", 1, "holding", 0, enum=["off", "heat"])
    assert [component(mode, False), component(mode, True)] == ["sensor", "select"]
    alarm = Point("a", "l", 1, "input", 0, bit=3)
    assert component(alarm, False) == "binary_sensor"


def test_home_assistant_hints_from_the_points() -> None:
    from pyrtu.bridge import parse_bridge_config
    from pyrtu.bridge.discovery import configs
    from pyrtu.bridge.topics import Topics

    text = """
[mqtt]
url = "mqtt://localhost"
edge = "e"
discovery = true
outbox = "/nonexistent/ob"
[[bus]]
name = "l"
port = "/dev/ttyX"
[[point]]
name = "power"
bus = "l"
slave = 1
table = "input"
address = 0
type = "float32"
unit = "W"
precision = 1
device_class = "power"
state_class = "measurement"
icon = "mdi:flash"
[[point]]
name = "mode"
bus = "l"
slave = 1
table = "holding"
address = 2
enum = { 0 = "off", 1 = "heat", 2 = "cool" }
writable = true
[[point]]
name = "state"
bus = "l"
slave = 1
table = "input"
address = 3
enum = ["idle", "run"]
[[point]]
name = "level"
bus = "l"
slave = 1
table = "holding"
address = 4
type = "float64"
precision = 2
writable = true
"""
    cfg = parse_bridge_config(text, "b.toml")
    docs = {json.loads(p)["name"]: (t, json.loads(p)) for t, p in configs(cfg, Topics(cfg))}
    topic, power = docs["power"]
    assert "/sensor/" in topic
    hints = ("unit_of_measurement", "device_class", "state_class", "icon")
    assert {k: power[k] for k in hints} == {
        "unit_of_measurement": "W", "device_class": "power", "state_class": "measurement",
        "icon": "mdi:flash",
    }  # fmt: skip
    assert power["suggested_display_precision"] == 1
    topic, mode = docs["mode"]
    assert "/select/" in topic and mode["options"] == ["off", "heat", "cool"]
    assert mode["command_template"] == "{{ value | tojson }}"
    topic, state = docs["state"]
    assert "/sensor/" in topic and state["device_class"] == "enum"
    assert state["options"] == ["idle", "run"]
    _, level = docs["level"]
    assert level["step"] == 0.01 and level["max"] == 1.7976931348623157e308
