"""Device templates from the command line (#29.1, #29.3, #29.4, #29.6): ``pyrtu
template list|show|check``, a template dropped into a folder of
``PYRTU_TEMPLATE_PATH`` used by every command, ``pyrtu simulate --template`` on a
pseudo-terminal and on Modbus TCP (reads, writes refused with the exception a
device gives, FC 43 identity), ``scan --identify``, ``read --profile``, the poller
and the bridge with Home Assistant discovery against a real mosquitto."""

from __future__ import annotations

import json
import shutil
import signal
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from cli_helpers import kill_after_each_test
from peers.tools import peer_env

from pyrtu import ExceptionResponseError, Master

pytest_plugins = ["peers.fixtures"]

SDM630 = Path(__file__).resolve().parents[1] / "devices" / "data" / "meters" / "sdm630.toml"


def f32(value: float) -> list[int]:
    """A float32 as two registers, high word first (``struct``, not pyrtu)."""
    return list(struct.unpack(">HH", struct.pack(">f", value)))


def run(
    *args: object, env: dict[str, str] | None = None, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", *map(str, args)],
        capture_output=True, text=True, timeout=timeout, env=env or peer_env(),
    )  # fmt: skip


@pytest.fixture
def folder(tmp_path: Path) -> Iterator[dict[str, str]]:
    """A user template folder holding meters/sdm630.toml, and its environment."""
    (tmp_path / "templates" / "meters").mkdir(parents=True)
    shutil.copy(SDM630, tmp_path / "templates" / "meters" / "sdm630.toml")
    env = peer_env()
    env["PYRTU_TEMPLATE_PATH"] = str(tmp_path / "templates")
    yield env


STARTED: list[subprocess.Popen[str]] = []
_nothing_left = kill_after_each_test(STARTED)


def simulate(*args: object, env: dict[str, str] | None = None) -> dict[str, Any]:
    """``pyrtu simulate ARGS --json`` in the background; its "ready" line."""
    p = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", *map(str, args), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env or peer_env(),
    )  # fmt: skip
    STARTED.append(p)
    assert p.stdout is not None
    line = p.stdout.readline()
    assert line, p.stderr.read() if p.stderr else ""
    ready: dict[str, Any] = json.loads(line)
    ready["proc"] = p
    return ready


def stop(ready: dict[str, Any]) -> str:
    p: subprocess.Popen[str] = ready["proc"]
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=15)
    assert p.returncode == 0, err
    return out


# -- pyrtu template ------------------------------------------------------------------


def test_a_dropped_in_template_is_listed_shown_and_checked(folder: dict[str, str]) -> None:
    plain = run("template", "list")
    assert plain.returncode == 0 and "meters/sdm630" not in plain.stdout
    assert [line.split()[0] for line in plain.stdout.splitlines()] == [
        "act", "acu", "cfw100", "cfw320", "cfw701", "cv100"
    ]  # fmt: skip
    listed = run("template", "list", "--json", env=folder)
    doc = json.loads(listed.stdout)
    names = [t["name"] for t in doc["templates"]]
    assert names == ["act", "acu", "cfw100", "cfw320", "cfw701", "cv100", "meters/sdm630"]
    meter = doc["templates"][-1]
    assert (meter["vendor"], meter["model"], meter["points"], meter["builtin"]) == (
        "Eastron", "SDM630", 9, False
    )  # fmt: skip
    shown = run("template", "show", "meters/sdm630", "--json", env=folder)
    t = json.loads(shown.stdout)["template"]
    assert t["identify"] == {"vendor": "Eastron", "product": "SDM630", "revision": "1.02"}
    assert t["points"][0] == {
        "name": "voltage_l1", "table": "input", "address": 0, "type": "float32", "unit": "V",
        "device_class": "voltage", "state_class": "measurement", "precision": 1,
        "initial": 230.5,
    }  # fmt: skip
    text = run("template", "show", "cfw701")
    assert text.returncode == 0 and "current" in text.stdout and "x0.1" in text.stdout


def test_check_says_file_line_and_key_and_exits_2(tmp_path: Path) -> None:
    good = run("template", "check", SDM630)
    assert good.returncode == 0 and good.stdout.strip().endswith("ok: Eastron SDM630, 9 points")
    text = SDM630.read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('unit = "Hz"', 'unit = "Hz"\nscale = "fast"'))
    line = bad.read_text().splitlines().index('scale = "fast"') + 1
    got = run("template", "check", SDM630, bad)
    assert got.returncode == 2
    assert f'{bad}:{line}: point[3] ("frequency"): scale: must be a finite number' in got.stderr
    assert "Traceback" not in got.stderr
    missing = run("template", "show", "meters/nothing")
    assert missing.returncode == 2 and "no template named 'meters/nothing'" in missing.stderr
    assert run("template", "check", tmp_path / "none.toml").returncode == 2


# -- simulate --template -----------------------------------------------------------------


def test_simulate_template_on_a_serial_port(pty_pair: tuple[str, str], tmp_path: Path) -> None:
    master_side, device_side = pty_pair
    values = tmp_path / "values.toml"
    values.write_text("voltage_l2 = 229.0\ndisplay_mode = 2\n")
    ready = simulate("--template", SDM630, "--values", values, "--port", device_side,
                     "--parity", "N", "--baudrate", "115200")  # fmt: skip
    assert (ready["device"], ready["address"]) == ("sdm630", 1)
    assert 43 in ready["functions"]
    with Master(master_side, baudrate=115200, parity="N", timeout=1.0) as m:
        # the initial values, as a big-endian single encodes them (struct)
        assert m.read_input_registers(1, 0, 4) == f32(230.5) + f32(229.0)
        assert m.read_input_registers(1, 6, 2) == f32(4.75)
        assert m.read_input_registers(1, 4, 2) == [0, 0]  # a hole inside max_gap (10): zeros
        with pytest.raises(ExceptionResponseError) as info:
            m.read_input_registers(1, 0x20, 2)  # no point there, beyond max_gap
        assert info.value.code == 2
        assert m.read_holding_registers(1, 0x10, 1) == [2]  # from --values
        assert m.read_holding_registers(1, 0xFC00, 3) == [19283746 >> 16, 19283746 & 0xFFFF, 0x70]
        # writes: within min..max, stored; outside, exception 3 and nothing stored
        m.write_register(1, 0x10, 3)
        assert m.read_holding_registers(1, 0x10, 1) == [3]
        for bad in (0, 4):
            with pytest.raises(ExceptionResponseError) as info:
                m.write_register(1, 0x10, bad)
            assert info.value.code == 3
        assert m.read_holding_registers(1, 0x10, 1) == [3]
        m.write_registers(1, 2, f32(30.0))
        assert m.read_holding_registers(1, 2, 2) == f32(30.0)
        with pytest.raises(ExceptionResponseError) as info:
            m.write_registers(1, 2, f32(60.5))  # max = 60
        assert info.value.code == 3
        assert m.read_holding_registers(1, 2, 2) == f32(30.0)
        m.write_registers(1, 2, f32(60.0))  # exactly the bound
        # not writable: exception 2, as for an address no point covers
        for address in (0xFC00, 0x11):
            with pytest.raises(ExceptionResponseError) as info:
                m.write_register(1, address, 1)
            assert info.value.code == 2
        assert m.read_holding_registers(1, 0xFC00, 1) == [19283746 >> 16]
        # FC 43: the template's identity
        assert m.read_device_identification(1) == {0: b"Eastron", 1: b"SDM630", 2: b"1.02"}
    out = stop(ready)
    assert json.loads(out.splitlines()[-1])["counters"]["exceptions"] == 6


def test_simulate_a_dropped_in_template_by_name_over_tcp(folder: dict[str, str]) -> None:
    ready = simulate("meters/sdm630", "--tcp", "127.0.0.1:0", "--address", "7", env=folder)
    assert ready["device"] == "meters/sdm630" and ready["port"] is None
    with Master(f"tcp://{ready['tcp']}", timeout=2.0) as m:
        assert m.read_input_registers(7, 0x46, 2) == f32(50.0)
        assert m.read_device_identification(7)[1] == b"SDM630"
        with pytest.raises(ExceptionResponseError) as info:
            m.write_register(7, 0x10, 9)
        assert info.value.code == 3
    # read --profile names the registers with the template's points
    got = run("read", f"tcp://{ready['tcp']}", "--slave", "7", "--table", "input", "0", "4",
              "--profile", "meters/sdm630", "--json", env=folder)  # fmt: skip
    assert got.returncode == 0, got.stderr
    notes = json.loads(got.stdout)["notes"]
    assert notes == {"0": "voltage_l1 = 230.5 V", "2": "voltage_l2 = 231.25 V"}
    unknown = run("read", f"tcp://{ready['tcp']}", "0", "--profile", "meters/sdm630")
    assert unknown.returncode == 2 and "no template named 'meters/sdm630'" in unknown.stderr
    stop(ready)


def test_simulate_template_errors_are_usage_errors(tmp_path: Path) -> None:
    values = tmp_path / "values.toml"
    values.write_text("voltage_l1 = 1.0\ncolour = 3\n")
    got = run("simulate", "--template", SDM630, "--values", values, "--tcp", "127.0.0.1:0")
    assert got.returncode == 2 and f"{values}:2: colour: no such point" in got.stderr
    values.write_text("display_mode = 70000\n")
    got = run("simulate", "--template", SDM630, "--values", values, "--tcp", "127.0.0.1:0")
    assert (
        got.returncode == 2
        and f"{values}:1: display_mode: 70000 is outside its min..max (1..3)" in got.stderr
    )
    both = run("simulate", "cfw701", "--template", SDM630, "--tcp", "127.0.0.1:0")
    assert both.returncode == 2 and "not both" in both.stderr
    drive = run("simulate", "cfw701", "--values", values, "--tcp", "127.0.0.1:0")
    assert drive.returncode == 2 and "--values" in drive.stderr


# -- scan --identify -----------------------------------------------------------------------


def test_scan_identify_names_the_template_by_identity_and_by_probe(
    folder: dict[str, str], tmp_path: Path
) -> None:
    by_identity = simulate("meters/sdm630", "--tcp", "127.0.0.1:0", env=folder)
    # the same meter without FC 43: only its probe register (0xFC02 = 0x0070) names it
    quiet = tmp_path / "quiet.toml"
    quiet.write_text(
        SDM630.read_text()
        .replace('identify = { vendor = "Eastron", product = "SDM630", revision = "1.02" }\n', "")
        .replace("address = 1\n", "address = 1\nfunctions = [3, 4, 6, 16]\n")
    )
    by_probe = simulate("--template", quiet, "--tcp", "127.0.0.1:0")
    for ready, template, how in ((by_identity, "meters/sdm630", "identity"),
                                 (by_probe, "meters/sdm630", "probe")):  # fmt: skip
        got = run("scan", f"tcp://{ready['tcp']}", "--range", "1", "--identify", "--json",
                  env=folder)  # fmt: skip
        assert got.returncode == 0, got.stderr
        (found,) = json.loads(got.stdout)["found"]
        assert (found["template"], found["matched_by"]) == (template, how)
        text = run("scan", f"tcp://{ready['tcp']}", "--range", "1", "--identify", env=folder)
        assert f"template {template} (by {how})" in text.stdout
    # a file in the folder that is not a template: named in a warning, left out
    notes = tmp_path / "templates" / "notes.toml"
    notes.write_text('[[bus]]\nname = "x"\n')
    got = run("scan", f"tcp://{by_identity['tcp']}", "--range", "1", "--identify", env=folder)
    assert got.returncode == 0 and "template meters/sdm630 (by identity)" in got.stdout
    assert f"warning: {notes}:1: unknown top-level key 'bus'" in got.stderr
    plain = run("scan", f"tcp://{by_probe['tcp']}", "--range", "1", "--identify", "--json")
    (found,) = json.loads(plain.stdout)["found"]  # without the user's folder: no match
    assert found["template"] is None
    stop(by_identity)
    stop(by_probe)


# -- the poller ------------------------------------------------------------------------------


def test_poll_a_dropped_in_template_device_end_to_end(
    pty_pair: tuple[str, str], tmp_path: Path, folder: dict[str, str]
) -> None:
    master_side, device_side = pty_pair
    ready = simulate("--template", SDM630, "--port", device_side, "--address", "4",
                     "--parity", "N", "--baudrate", "115200")  # fmt: skip
    config = tmp_path / "poll.toml"
    config.write_text(f"""
[[bus]]
name = "line"
port = "{master_side}"
baudrate = 115200
parity = "N"
timeout = 0.5

[[device]]
bus = "line"
slave = 4
template = "meters/sdm630"
name = "meter"
interval = 0.05
""")
    got = run("poll", "--config", config, "--duration", "1.5", "--json", env=folder, timeout=60)
    assert got.returncode == 0, got.stderr
    values: dict[str, Any] = {}
    for line in got.stdout.splitlines():
        doc = json.loads(line)
        if "point" in doc and "value" in doc:
            values[doc["point"]] = doc["value"]
    assert values["meter.voltage_l1"] == 230.5 and values["meter.energy_total"] == 1234.5
    assert values["meter.display_mode"] == 1 and values["meter.serial_number"] == 19283746
    stop(ready)


# -- the bridge and Home Assistant -------------------------------------------------------------


def test_bridge_with_home_assistant_discovery_from_a_template(tmp_path: Path) -> None:
    from mqtt_broker import Broker, Client, need_mosquitto

    need_mosquitto()
    ready = simulate("--template", SDM630, "--tcp", "127.0.0.1:0")
    with Broker(tmp_path) as broker:
        config = tmp_path / "bridge.toml"
        config.write_text(f"""
[mqtt]
url = "{broker.url}"
edge = "e1"
discovery = true

[[bus]]
name = "net"
port = "tcp://{ready["tcp"]}"
timeout = 1.0

[[device]]
bus = "net"
slave = 1
template = "{SDM630}"
name = "meter"
interval = 0.05
""")
        with Client(broker, ["homeassistant/#", "pyrtu/#"]) as sub:
            p = subprocess.Popen(
                [sys.executable, "-m", "pyrtu", "bridge", "--config", str(config)],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
            )  # fmt: skip
            STARTED.append(p)
            sub.wait(
                lambda: sum(m[0].startswith("homeassistant/") for m in sub.messages) >= 9,
                "9 discovery configs",
            )
            docs = {t: json.loads(m) for t, m, *_ in sub.messages if t.startswith("homeassistant/")}
            volts = docs["homeassistant/sensor/pyrtu_e1/net_1_meter_voltage_l1/config"]
            assert volts["unit_of_measurement"] == "V" and volts["device_class"] == "voltage"
            assert volts["state_class"] == "measurement"
            assert volts["suggested_display_precision"] == 1
            assert volts["device"]["manufacturer"] == "Eastron"
            assert volts["device"]["model"] == "SDM630" and volts["device"]["name"] == "meter"
            energy = docs["homeassistant/sensor/pyrtu_e1/net_1_meter_energy_total/config"]
            assert (
                energy["state_class"] == "total_increasing"
                and energy["unit_of_measurement"] == "kWh"
            )
            period = docs["homeassistant/number/pyrtu_e1/net_1_meter_demand_period/config"]
            assert (period["min"], period["max"]) == (0, 60)
            # no empty hint: Home Assistant refuses a config with `"device_class": ""`
            # or `"icon": ""` (a key without a value is left out)
            for doc in docs.values():
                assert not [k for k, v in doc.items() if v == ""], doc
            # one Home Assistant device for the meter
            assert len({json.dumps(d["device"]["identifiers"]) for d in docs.values()}) == 1
            topic = "pyrtu/e1/net/1/meter.voltage_l1"
            sub.wait(lambda: bool(sub.on(topic)), "a value")
            assert json.loads(sub.on(topic)[-1])["value"] == 230.5
            # a command as Home Assistant sends it, written to the simulated meter
            sub.publish(period["command_topic"], b"45.0")
            results = "pyrtu/e1/net/1/meter.demand_period/set/result"
            sub.wait(lambda: len(sub.on(results)) >= 1, "the result")
            assert json.loads(sub.on(results)[0])["ok"] is True
            with Master(f"tcp://{ready['tcp']}", timeout=2.0) as m:
                assert m.read_holding_registers(1, 2, 2) == f32(45.0)
            # out of the template's range: refused before a byte is sent
            sub.publish(period["command_topic"], b"61")
            sub.wait(lambda: len(sub.on(results)) >= 2, "the refusal")
            refused = json.loads(sub.on(results)[1])
            assert refused["ok"] is False and "60" in json.dumps(refused)
            with Master(f"tcp://{ready['tcp']}", timeout=2.0) as m:
                assert m.read_holding_registers(1, 2, 2) == f32(45.0)
            p.send_signal(signal.SIGTERM)
            _, err = p.communicate(timeout=30)
            assert p.returncode == 0, err
    stop(ready)


# -- info and sniff in a template's terms -------------------------------------------------


def test_info_profile_says_whether_the_device_is_the_template(folder: dict[str, str]) -> None:
    ready = simulate("meters/sdm630", "--tcp", "127.0.0.1:0", env=folder)
    got = run("info", f"tcp://{ready['tcp']}", "--slave", "1", "--profile", "meters/sdm630",
              "--json", env=folder)  # fmt: skip
    assert got.returncode == 0, got.stderr
    ident = json.loads(got.stdout)["identification"]
    assert ident["VendorName"] == "Eastron" and ident["template"] == "meters/sdm630"
    assert (ident["matches"], ident["matched_by"]) == ("yes", "identity")
    sdm120 = Path(folder["PYRTU_TEMPLATE_PATH"]) / "sdm120.toml"
    sdm120.write_text(SDM630.read_text().replace('product = "SDM630"', 'product = "SDM120"'))
    other = run("info", f"tcp://{ready['tcp']}", "--slave", "1", "--profile", "sdm120",
                "--json", env=folder)  # fmt: skip
    ident = json.loads(other.stdout)["identification"]
    assert other.returncode == 0 and (ident["matches"], ident["ProductCode"]) == ("no", "SDM630")
    stop(ready)


def test_sniff_names_a_templates_registers() -> None:
    from pyrtu.cli.sniff import Decoder, Seen

    decoder = Decoder(str(SDM630))
    request = bytes([1, 4, 0, 0, 0, 4])
    data = b"".join(struct.pack(">f", v) for v in (230.5, 231.25))
    response = bytes([1, 4, 8]) + data
    decoder.decode(Seen("request", request, request, None))
    got = decoder.decode(Seen("response", response, response, None))
    assert got.notes == ["voltage_l1 = 230.5 V", "voltage_l2 = 231.25 V"]
    assert Decoder("cfw701").decode(Seen("request", bytes([1, 3, 2, 0xA8, 0, 1]), b"", None))
