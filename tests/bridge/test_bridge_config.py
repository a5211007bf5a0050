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
    assert cfg.option("weg.ref") == PointOptions(max_age=5)
    ref = next(p for p in cfg.poller.points if p.name == "weg.ref")
    assert (ref.writable, ref.min, ref.max) == (True, 0, 8192)
    assert cfg.max_age("weg.ref") == 5 and cfg.max_age("weg.status") == 30
    assert not next(p for p in cfg.poller.points if p.name == "weg.status").writable
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
            "point[1] (\"flag\"): topic: 'plant/+/flag' holds the wildcard '+'",
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
        (  # the bridge's own keys are known too (#27.14)
            ("address = 683", "adress = 683"),
            "b.toml:23:",
            "(known: name, bus, slave, table, address, type, order, count, scale, offset, "
            "interval, deadband, unit, precision, enum, bit, bits, error_value, "
            "unsupported_value, writable, min, max, device_class, state_class, icon, topic, "
            "max_age)",
        ),
        (
            ("max_age = 30", "max_age = 30\n[defaults]\nwritabel = true"),
            "b.toml:6:",
            "defaults: writabel: unknown key (known: bus, slave, table, type, order, count, "
            "scale, offset, interval, deadband, unit, precision, enum, bit, bits, error_value, "
            "unsupported_value, writable, min, max, device_class, state_class, icon, max_age)",
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
    (tmp_path / "pw").write_text("s3cret\n")
    cfg = load_bridge_config(f)
    assert cfg.mqtt.password_file == str(tmp_path / "pw")
    assert cfg.mqtt.outbox == str(tmp_path / "outbox-e1")
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
    rw_cfg = parse_bridge_config(rw, "b.toml")
    assert next(p for p in rw_cfg.poller.points if p.name == "weg.status").writable
    ro = rw + '[[point]]\nname = "in"\nbus = "line"\nslave = 3\ntable = "input"\naddress = 0\n'
    with pytest.raises(ConfigError, match=r"writable: the input table is read only \(from \[defa"):
        parse_bridge_config(ro, "b.toml")


#: names MQTT does not allow in a topic level (MQTT 5.0 4.7.1 wildcards, 4.7.3 and
#: 1.5.4: no U+0000, control characters and non-characters SHOULD NOT be used and
#: mosquitto refuses them; a '/' would be a second level)
BAD_LEVELS = ["a+b", "x#", "#", "+", "a/b", "/", "a\u0000b", "a\nb", "a\u0001", "a\u001f",
              "a\u007f", "a\u0080", "a\u009f", "a\ufffe", "a\uffff", "a\ufdd0",
              "a\U0010ffff"]  # fmt: skip
#: the first characters past each forbidden range, and names of other scripts
GOOD_LEVELS = ["a b", "a\u00a0", "a\ufdcf", "a\ufdf0", "a\ufffd", "é", "温度", "a😀", "$a",
               "a.b-c_d"]  # fmt: skip


def _toml_string(text: str) -> str:
    """A TOML basic string: printable ASCII as is, the rest escaped (TOML 1.0)."""
    plain = (c if " " <= c <= "~" and c not in '"\\' else f"\\U{ord(c):08X}" for c in text)
    return '"' + "".join(plain) + '"'


def _point(name: str, topic: str | None = None) -> str:
    own = f"topic = {_toml_string(topic)}\n" if topic is not None else ""
    return (
        f'[[point]]\nname = {_toml_string(name)}\nbus = "line"\nslave = 3\n'
        f'table = "holding"\naddress = 9\n{own}'
    )


@pytest.mark.parametrize("name", BAD_LEVELS)
def test_a_name_that_is_not_one_topic_level_is_refused_at_its_line(name: str) -> None:
    # a point's name (#27.1): the line of its name
    text = GOOD + _point(name)
    with pytest.raises(ConfigError) as e:
        parse_bridge_config(text, "b.toml")
    line = text.splitlines().index(f"name = {_toml_string(name)}") + 1
    assert str(e.value).startswith(f"b.toml:{line}: point[2] ("), str(e.value)
    assert "): name: " in str(e.value)
    # a bus's name
    text = GOOD.replace('name = "line"', f"name = {_toml_string(name)}").replace(
        'bus = "line"', f"bus = {_toml_string(name)}"
    )
    with pytest.raises(ConfigError) as e:
        parse_bridge_config(text, "b.toml")
    assert str(e.value).startswith("b.toml:8: bus[0] ("), str(e.value)
    assert "): name: " in str(e.value)
    # a device's name, the first part of its points' names
    text = GOOD.replace('name = "weg"', f"name = {_toml_string(name)}")
    with pytest.raises(ConfigError) as e:
        parse_bridge_config(text, "b.toml")
    assert str(e.value).startswith("b.toml:16: device[0]: name: "), str(e.value)


@pytest.mark.parametrize("name", GOOD_LEVELS)
def test_a_name_that_is_one_topic_level_is_taken(name: str) -> None:
    cfg = parse_bridge_config(GOOD + _point(name), "b.toml")
    assert Topics(cfg).point[name] == f"pyrtu/e1/line/3/{name}"


def test_a_point_with_its_own_topic_may_have_any_name_but_the_topic_is_checked() -> None:
    cfg = parse_bridge_config(GOOD + _point("a+b/c", "plant/a-b"), "b.toml")
    assert Topics(cfg).point["a+b/c"] == "plant/a-b"
    for topic in ("plant/x#", "plant//x", "/plant", "plant/", "$SYS/x", "plant/\u0000"):
        with pytest.raises(ConfigError, match=r"^b.toml:\d+: point\[2\] .*: topic: "):
            parse_bridge_config(GOOD + _point("p", topic), "b.toml")


def test_edge_and_prefix_follow_the_same_rule() -> None:
    for key, value in (("edge", "e+1"), ("edge", "e/1"), ("edge", "e\u0001"),
                       ("prefix", "$SYS"), ("prefix", "a//b"), ("prefix", "p#"),
                       ("discovery_prefix", "$ha")):  # fmt: skip
        text = GOOD.replace('edge = "e1"', f'edge = "e1"\n{key} = {_toml_string(value)}')
        if key == "edge":
            text = GOOD.replace('edge = "e1"', f"edge = {_toml_string(value)}")
        line = 3 if key == "edge" else 4
        with pytest.raises(ConfigError, match=rf"^b.toml:{line}: mqtt: {key}: "):
            parse_bridge_config(text, "b.toml")


def test_the_python_api_refuses_the_same_names() -> None:
    from pyrtu.bridge import make_bridge_config

    cfg = parse_bridge_config(GOOD + _point("a+b", "plant/a-b"), "b.toml")
    with pytest.raises(ConfigError, match=r"point 'a\+b': name: 'a\+b' holds the wildcard '\+'"):
        make_bridge_config(cfg.poller, cfg.mqtt)  # without its topic


@pytest.mark.parametrize("name", ["a+b", "x#", "a/b"])
def test_check_and_a_run_exit_2_on_a_point_name_that_is_not_a_topic_level(
    tmp_path: Path, name: str
) -> None:
    f = tmp_path / "b.toml"
    f.write_text(GOOD + _point(name))
    line = f.read_text().splitlines().index(f"name = {_toml_string(name)}") + 1
    for args in (("--check", str(f)), ("--config", str(f), "--duration", "1")):
        r = _cli(*args)
        assert r.returncode == 2, r.stderr
        assert f"b.toml:{line}: point[2] (" in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "outbox-e1").exists()  # before anything is opened


@pytest.mark.parametrize("key", ["password_file", "ca", "cert", "key"])
def test_a_file_key_naming_no_file_is_an_error_at_its_line(tmp_path: Path, key: str) -> None:
    extra = {"password_file": 'username = "u"\npassword_file = "missing"',
             "ca": 'ca = "missing"', "cert": 'cert = "missing"\nkey = "k.pem"',
             "key": 'cert = "c.pem"\nkey = "missing"'}[key]  # fmt: skip
    (tmp_path / "k.pem").write_text("x")
    (tmp_path / "c.pem").write_text("x")
    (tmp_path / "a-directory").mkdir()
    text = GOOD.replace("mqtt://", "mqtts://").replace('edge = "e1"', f'edge = "e1"\n{extra}')
    f = tmp_path / "b.toml"
    f.write_text(text)
    line = next(n for n, t in enumerate(text.splitlines(), 1) if t.startswith(f"{key} ="))
    r = _cli("--check", str(f))
    assert r.returncode == 2, r.stdout
    want = f"b.toml:{line}: mqtt: {key}: {tmp_path / 'missing'}: no such file"
    assert want in r.stderr and "Traceback" not in r.stderr
    f.write_text(text.replace('"missing"', '"a-directory"'))
    with pytest.raises(ConfigError, match=rf"^b.toml:{line}: mqtt: {key}: .*: not a regular file"):
        load_bridge_config(f)
    (tmp_path / "missing").write_text("there now\n")
    f.write_text(text)
    assert _cli("--check", str(f)).returncode == 0


def test_a_template_devices_own_writable_min_max_win_over_defaults(tmp_path: Path) -> None:
    """A ``[[device]]`` from a template loads (its points carry writable, min and max);
    ``[defaults]`` gives them only to the points whose template says nothing."""
    (tmp_path / "tc.toml").write_text(
        '[device]\nvendor = "Acme"\nmodel = "TC-10"\n\n'
        '[[point]]\nname = "setpoint"\ntable = "holding"\naddress = 16\n'
        "writable = true\nmin = 0\nmax = 400\n\n"
        '[[point]]\nname = "mode"\ntable = "holding"\naddress = 17\n\n'
        '[[point]]\nname = "locked"\ntable = "holding"\naddress = 18\nwritable = false\n'
    )
    text = (
        '[mqtt]\nurl = "mqtt://127.0.0.1:1883"\nedge = "e1"\n\n'
        "[defaults]\nwritable = true\nmax = 100\n\n"
        '[[bus]]\nname = "line"\nport = "/dev/null-not-opened"\n\n'
        '[[device]]\nbus = "line"\nslave = 1\ntemplate = "tc.toml"\nname = "oven"\n'
    )
    (tmp_path / "b.toml").write_text(text)
    cfg = load_bridge_config(tmp_path / "b.toml")
    points = {p.name: p for p in cfg.poller.points}
    assert (points["oven.setpoint"].writable, points["oven.setpoint"].max) == (True, 400)
    assert (points["oven.mode"].writable, points["oven.mode"].max) == (True, 100)
    assert points["oven.locked"].writable is False
    assert cfg.drives == {("line", 1): ("tc", "oven")}
