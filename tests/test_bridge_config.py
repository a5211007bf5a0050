"""The bridge's configuration: the poller's TOML plus [mqtt] and per-point keys;
every error names the file, the line and the key, before anything is opened
(``pyrtu bridge --check`` exits 2 on them, 0 on a good file)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from pyrtu.bridge import MqttConfig, PointOptions, load_bridge_config, parse_bridge_config
from pyrtu.bridge.topics import Topics
from pyrtu.poller import ConfigError

GOOD = """\
[mqtt]
url = "mqtt://127.0.0.1:1883"
edge = "e1"
qos = 1
max_age = 30

[[bus]]
name = "line"
port = "/dev/null-not-opened"
baudrate = 19200

[[device]]
bus = "line"
slave = 1
profile = "cfw701"
name = "weg"

[[point]]
name = "weg.ref"
bus = "line"
slave = 1
table = "holding"
address = 683
writable = true
min = 0
max = 8192
max_age = 5

[[point]]
name = "flag"
bus = "line"
slave = 2
table = "coils"
address = 0
writable = true
topic = "plant/hall1/flag"
"""


def test_a_good_file_gives_the_poller_its_points_and_the_bridge_its_keys() -> None:
    cfg = parse_bridge_config(GOOD, "b.toml")
    names = [p.name for p in cfg.poller.points]
    assert "weg.status" in names and "weg.ref" in names and "flag" in names
    assert cfg.mqtt.edge == "e1" and cfg.mqtt.qos == 1 and cfg.mqtt.port == 1883
    assert cfg.option("weg.ref") == PointOptions(writable=True, min=0, max=8192, max_age=5)
    assert cfg.max_age("weg.ref") == 5 and cfg.max_age("weg.status") == 30
    assert not cfg.option("weg.status").writable
    t = Topics(cfg)
    assert t.point["weg.ref"] == "pyrtu/e1/line/1/weg.ref"
    assert t.point["flag"] == "plant/hall1/flag"
    assert t.slave_status[("line", 2)] == "pyrtu/e1/line/2/status"
    assert t.set["plant/hall1/flag/set"] == "flag"
    assert t.extra_set_topics() == ["plant/hall1/flag/set"]


@pytest.mark.parametrize(
    ("change", "where", "message"),
    [
        (("qos = 1", "qos = 3"), "b.toml:4:", "mqtt: qos: must be an integer 0..2, not 3"),
        (("qos = 1", "qso = 1"), "b.toml:4:", "mqtt: qso: unknown key"),
        (('url = "mqtt://127.0.0.1:1883"', 'url = "http://x"'), "b.toml:2:", "mqtt: url:"),
        (("max_age = 30", "max_age = -1"), "b.toml:5:", "mqtt: max_age: must be a non-negative"),
        (
            ("writable = true\nmin = 0", "writable = 1\nmin = 0"),
            "b.toml:24:",
            'point[0] ("weg.ref"): writable: must be true or false',
        ),
        (
            ("min = 0\nmax = 8192", "min = 10\nmax = 5"),
            "b.toml:26:",
            'point[0] ("weg.ref"): max: must be at least min',
        ),
        (
            ('topic = "plant/hall1/flag"', 'topic = "plant/+/flag"'),
            "b.toml:36:",
            'point[1] ("flag"): topic: must be a non-empty string without +',
        ),
        (
            ('table = "coils"', 'table = "discrete_inputs"'),
            "b.toml:35:",
            "writable: the discrete_inputs table is read only",
        ),
        (
            ("address = 683", "adress = 683"),
            "b.toml:23:",
            'point[0] ("weg.ref"): adress: unknown key',
        ),
        (
            ('topic = "plant/hall1/flag"', 'topic = "pyrtu/e1/line/1/weg.ref"'),
            "b.toml:",
            "topic 'pyrtu/e1/line/1/weg.ref' is also point 'weg.ref'",
        ),
    ],
)
def test_errors_name_the_file_the_line_and_the_key(
    change: tuple[str, str], where: str, message: str
) -> None:
    text = GOOD.replace(*change, 1)
    assert text != GOOD
    with pytest.raises(ConfigError) as e:
        parse_bridge_config(text, "b.toml")
    assert str(e.value).startswith(where), str(e.value)
    assert message in str(e.value), str(e.value)


def test_no_mqtt_table_and_secrets() -> None:
    with pytest.raises(ConfigError, match=r"b.toml: no \[mqtt\] table"):
        parse_bridge_config(
            GOOD.split("[[bus]]")[0].replace("[mqtt]", "[other]")
            + "[[bus]]"
            + GOOD.split("[[bus]]")[1],
            "b.toml",
        )
    with pytest.raises(ValueError, match="password_file: give password or password_file"):
        MqttConfig("mqtt://h", username="u", password="p", password_file="/x")
    with pytest.raises(ValueError, match="username: a password needs a username"):
        MqttConfig("mqtt://h", password="p")
    with pytest.raises(ValueError, match="ca: TLS files need an mqtts:// url"):
        MqttConfig("mqtt://h", ca="/ca.pem")
    m = MqttConfig("mqtts://broker.example", username="u", password="hunter2", edge="e")
    assert m.port == 8883 and m.tls and "hunter2" not in repr(m)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", "bridge", *args], capture_output=True, text=True, timeout=60
    )


def test_check_validates_without_opening_anything(tmp_path: Path) -> None:
    good = tmp_path / "b.toml"
    good.write_text(GOOD)
    r = _cli("--check", str(good), "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["ok"] is True and doc["points"] == 7 and doc["writable"] == 2
    assert not (tmp_path / "outbox-e1").exists()  # nothing opened or made
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace("qos = 1", "qos = 7"))
    r = _cli("--check", str(bad))
    assert r.returncode == 2
    assert "bad.toml:4: mqtt: qos: must be an integer 0..2, not 7" in r.stderr
    assert "Traceback" not in r.stderr
    r = _cli("--config", str(bad))  # the same before anything is opened
    assert r.returncode == 2 and "bad.toml:4:" in r.stderr


def test_relative_paths_are_the_files_and_the_outbox_defaults_next_to_it(tmp_path: Path) -> None:
    f = tmp_path / "b.toml"
    f.write_text(GOOD.replace('edge = "e1"', 'edge = "e1"\nusername = "u"\npassword_file = "pw"'))
    cfg = load_bridge_config(f)
    assert cfg.mqtt.password_file == str(tmp_path / "pw")
    assert cfg.mqtt.outbox == str(tmp_path / "outbox-e1")
    (tmp_path / "pw").write_text("s3cret\n")
    assert cfg.mqtt.secret() == "s3cret"


def test_defaults_carry_bridge_keys_but_not_a_topic() -> None:
    text = GOOD.replace("[[bus]]", "[defaults]\nmax_age = 7\ndeadband = 0\n\n[[bus]]", 1)
    cfg = parse_bridge_config(text, "b.toml")
    assert cfg.max_age("weg.status") == 7  # a profile point too
    assert cfg.max_age("weg.ref") == 5  # its own key wins
    bad = GOOD.replace("[[bus]]", '[defaults]\ntopic = "x/y"\n\n[[bus]]', 1)
    with pytest.raises(ConfigError, match=r"^b.toml:8: defaults: topic: a topic is one point's"):
        parse_bridge_config(bad, "b.toml")
    rw = GOOD.replace("[[bus]]", "[defaults]\nwritable = true\n\n[[bus]]", 1)
    assert parse_bridge_config(rw, "b.toml").option("weg.status").writable
    ro = rw + '[[point]]\nname = "in"\nbus = "line"\nslave = 3\ntable = "input"\naddress = 0\n'
    with pytest.raises(ConfigError, match=r"writable: the input table is read only \(from \[defa"):
        parse_bridge_config(ro, "b.toml")
