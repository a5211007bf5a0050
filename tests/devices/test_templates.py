"""Device templates (#29.1, #29.3): the format, its JSON Schema, the registry, errors
naming file, line and key, and the six drives of the manuals as templates."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the test extra installs tomli there
    import tomli as tomllib

from pyrtu.devices import registry
from pyrtu.devices.registry import TemplateError, find_template, load_template, parse_template
from pyrtu.poller.config import ConfigError, parse_config, template_points
from pyrtu.poller.profiles import device_limits, profile_points

DATA = Path(__file__).parent / "data"
SDM630 = DATA / "meters" / "sdm630.toml"
BUILTIN = ("act", "acu", "cfw100", "cfw320", "cfw701", "cv100")


def test_every_shipped_template_validates_against_the_published_schema() -> None:
    import jsonschema  # the test extra (pyproject.toml)

    schema = json.loads(registry.SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    files = [*sorted(registry.BUILTIN_DIR.glob("*.toml")), SDM630]
    assert [f.stem for f in files[:-1]] == list(BUILTIN)
    for f in files:
        errors = list(validator.iter_errors(tomllib.loads(f.read_text())))
        assert errors == [], (f, [e.message for e in errors])
    # the schema refuses what the loader refuses (an unknown key, a bad type name)
    doc = tomllib.loads(SDM630.read_text())
    doc["point"][0]["colour"] = "red"
    assert any("colour" in e.message for e in validator.iter_errors(doc))
    doc = tomllib.loads(SDM630.read_text())
    doc["point"][0]["type"] = "float24"
    assert list(validator.iter_errors(doc))


def test_the_schema_lists_the_whole_key_set_of_the_issue() -> None:
    schema = json.loads(registry.SCHEMA_PATH.read_text())
    point = schema["$defs"]["point"]["properties"]
    for key in ("type", "order", "scale", "offset", "unit", "precision", "enum", "bit", "bits",
                "error_value", "unsupported_value", "writable", "min", "max", "interval",
                "deadband", "device_class", "state_class", "icon", "table", "address", "name",
                "count", "length", "initial"):  # fmt: skip
        assert key in point, key
    assert set(point["type"]["enum"]) == {
        "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float16",
        "float32", "float64", "string", "bool", "bcd16", "bcd32",
    }  # fmt: skip
    device = schema["properties"]["device"]["properties"]
    assert set(device) == set(registry.DEVICE_KEYS)


def test_the_builtin_drives_are_templates_with_their_manuals_registers() -> None:
    assert registry.builtin_names() == BUILTIN
    # the registers of the manuals (WEG P680/P002/P003/P049/P048; CV100 0x3300...;
    # Vectron 411/260/270), as their profiles polled them before they were data
    weg = profile_points("cfw701", "weg", "line", 1, 0.5)
    assert [(p.name, p.address, p.scale, p.interval) for p in weg] == [
        ("weg.status", 680, 1.0, 0.5), ("weg.speed", 2, 1.0, 0.5), ("weg.current", 3, 0.1, 0.5),
        ("weg.fault", 49, 1.0, 0.5), ("weg.alarm", 48, 1.0, 0.5),
    ]  # fmt: skip
    cv = profile_points("cv100", "cv", "line", 5)
    assert [(p.address, p.scale) for p in cv] == [
        (0x3300, 1.0),
        (0x3305, 0.01),
        (0x3306, 0.1),
        (0x3314, 1.0),
    ]
    assert [p.address for p in profile_points("acu", "a", "l", 2)] == [411, 260, 270]
    assert device_limits("cfw100") == {"max_adu": 64}
    assert device_limits("act") == {"max_registers": 1}
    assert device_limits("cv100") == {}
    from pyrtu.devices import ASCII_DEVICES, EXAMPLE_ADDRESS, SIMULATORS, CV100Simulator

    assert SIMULATORS["cv100"] is CV100Simulator and set(SIMULATORS) == set(BUILTIN)
    assert EXAMPLE_ADDRESS == {
        "act": 1,
        "acu": 1,
        "cfw100": 1,
        "cfw320": 1,
        "cfw701": 1,
        "cv100": 5,
    }
    assert ASCII_DEVICES == {"act", "acu", "cv100"}


def test_a_template_file_loads_with_its_device_keys() -> None:
    t = load_template(SDM630)
    assert (t.vendor, t.model, t.name, t.word_order) == ("Eastron", "SDM630", "sdm630", "ABCD")
    assert t.limits == {"max_registers": 40, "max_gap": 10}
    assert t.identification() == {0: b"Eastron", 1: b"SDM630", 2: b"1.02"}
    assert t.matches_identity({0: "eastron ", 1: "SDM630", 2: "1.02"})
    assert not t.matches_identity({0: "Eastron", 1: "SDM120", 2: "1.02"})
    assert t.probe == registry.Probe("holding", 0xFC02, 0x70)
    points, hints = template_points(t, "m1", "bus", 7)
    assert points[0].name == "m1.voltage_l1" and points[0].slave == 7 and points[0].bus == "bus"
    assert hints["m1.voltage_l1"]["unit"] == "V" and hints["m1.demand_period"]["writable"] is True
    # the decoding is the poller's: 230.5 as a big-endian single
    regs = struct.unpack(">HH", struct.pack(">f", 230.5))
    assert points[0].decode(list(regs), 0) == 230.5


def test_word_order_is_the_default_of_32_bit_points() -> None:
    text = SDM630.read_text().replace('word_order = "ABCD"', 'word_order = "CDAB"')
    points, _ = template_points(parse_template(text, "m.toml"))
    assert points[0].order == "CDAB"  # float32
    assert points[6].type == "uint16"  # the default order does not touch 16-bit points
    swapped = struct.unpack(">HH", struct.pack(">f", 4.75))[::-1]
    assert points[2].decode(list(swapped), 6) == 4.75


HEAD = '[device]\nvendor = "Acme"\nmodel = "T1"\n'
POINT = '\n[[point]]\nname = "temp"\ntable = "holding"\naddress = 0\n'


def bad_template(text: str) -> str:
    with pytest.raises(ValueError) as info:
        template_points(parse_template(text, "acme.toml"))
    assert isinstance(info.value, TemplateError | ConfigError)
    return str(info.value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (HEAD + "colour = 1\n" + POINT, "acme.toml:4: device: colour: unknown key"),
        (HEAD + 'word_order = "XYZW"\n' + POINT,
         "acme.toml:4: device: word_order: must be one of ABCD, CDAB, BADC, DCBA, not 'XYZW'"),
        (HEAD + "max_registers = 126\n" + POINT,
         "acme.toml:4: device: max_registers: must be an integer 1..125, not 126"),
        (HEAD + "max_registers = 0\n" + POINT,
         "acme.toml:4: device: max_registers: must be an integer 1..125, not 0"),
        (HEAD + 'identify = { vendor = "Acme", colour = "x" }\n' + POINT,
         "acme.toml:4: device: identify: colour: unknown key"),
        (HEAD + 'identify = { vendor = "Acme" }\nfunctions = [3, 6]\n' + POINT,
         "acme.toml:4: device: identify: needs function 43"),
        (HEAD + "probe = { address = 70000, value = 1 }\n" + POINT,
         "acme.toml:4: device: probe: address: must be an integer 0..65535, not 70000"),
        (HEAD + 'simulator = "os:system"\n' + POINT,
         "acme.toml:4: device: simulator: must be \"pyrtu.devices.MODULE"),
        ('[device]\nvendor = "Acme"\n' + POINT, "acme.toml:1: device: model: missing"),
        (HEAD, "acme.toml: no [[point]] table"),
        (HEAD + POINT + "colour = 1\n", 'acme.toml:9: point[0] ("temp"): colour: unknown key'),
        (HEAD + POINT + 'type = "float24"\n', 'acme.toml:9: point[0] ("temp"): type: must be'),
        (HEAD + POINT.replace("address = 0", "address = 65535") + 'type = "uint32"\n',
         'acme.toml:8: point[0] ("temp"): address: 65535 + 2 registers runs past'),
        (HEAD + POINT + 'unit = ""\n', 'acme.toml:9: point[0] ("temp"): unit: must be a non'),
        (HEAD + POINT + "slave = 3\n", 'acme.toml:9: point[0] ("temp"): slave: a template'),
        (HEAD + POINT.replace("holding", "input") + "writable = true\n",
         'acme.toml:9: point[0] ("temp"): writable: the input table is read only'),
        (HEAD + POINT + "min = 5\nmax = 1\n", 'acme.toml:10: point[0] ("temp"): max: must be'),
        (HEAD + POINT + "initial = 70000\n", 'acme.toml:9: point[0] ("temp"): initial: 70000'),
        (HEAD + POINT + "initial = 9\nmax = 8\n", 'acme.toml:9: point[0] ("temp"): initial: 9 is'),
        (HEAD + POINT + 'state_class = "sometimes"\n',
         'acme.toml:9: point[0] ("temp"): state_class: must be one of measurement, total'),
        (HEAD + POINT + POINT.replace("temp", "wide") + 'type = "uint32"\n',
         'acme.toml:13: point[1] ("wide"): address: holding 0..1 (uint32) overlaps point[0]'),
        (HEAD + POINT + POINT, "acme.toml: point: name: 'temp' is declared twice"),
        (HEAD + "[colour]\n" + POINT, "acme.toml:4: unknown top-level key 'colour'"),
        ("colour = 1\n" + HEAD + POINT, "acme.toml:1: unknown top-level key 'colour'"),
        (HEAD + POINT + "[[bus]]\nname = 1\n", "acme.toml:9: unknown top-level key 'bus'"),
    ],
)  # fmt: skip
def test_errors_name_the_file_the_line_and_the_key(text: str, expected: str) -> None:
    assert bad_template(text).startswith(expected)


def test_a_same_type_alias_is_not_an_overlap() -> None:
    text = HEAD + POINT + POINT.replace("temp", "temp_f") + "scale = 1.8\noffset = 32\n"
    points, _ = template_points(parse_template(text, "acme.toml"))
    assert [p.name for p in points] == ["temp", "temp_f"]


def test_the_registry_finds_names_files_and_user_folders(tmp_path: Path) -> None:
    user = tmp_path / "mine"
    (user / "meters").mkdir(parents=True)
    (user / "meters" / "sdm630.toml").write_text(SDM630.read_text())
    env = {registry.TEMPLATE_PATH_ENV: str(user)}
    assert registry.names(env) == ("act", "acu", "cfw100", "cfw320", "cfw701", "cv100",
                                   "meters/sdm630")  # fmt: skip
    assert find_template("meters/sdm630", environ=env).model == "SDM630"
    assert find_template("CFW701", environ=env).model == "CFW701"
    assert find_template("meters/sdm630.toml", user).model == "SDM630"  # a file, relative
    with pytest.raises(TemplateError, match="no template named 'meters/sdm120'"):
        find_template("meters/sdm120", environ=env)
    with pytest.raises(TemplateError, match=r"nope\.toml: no such file"):
        find_template("nope.toml", tmp_path)
    # a user folder comes first: its cfw701 shadows the built-in one
    (user / "cfw701.toml").write_text(SDM630.read_text())
    entry = registry.entries(env)["cfw701"]
    assert entry.path == user / "cfw701.toml" and not entry.builtin
    assert entry.shadows == (registry.BUILTIN_DIR / "cfw701.toml",)


def test_the_poller_config_takes_a_template_file_or_name(tmp_path: Path) -> None:
    (tmp_path / "meters").mkdir()
    (tmp_path / "meters" / "sdm630.toml").write_text(SDM630.read_text())
    text = (
        '[[bus]]\nname = "line"\nport = "/dev/null"\n\n'
        '[[device]]\nbus = "line"\nslave = 4\ntemplate = "meters/sdm630.toml"\nname = "meter"\n'
        "interval = 0.5\nmax_registers = 20\n\n"
        '[[device]]\nbus = "line"\nslave = 1\ntemplate = "cfw701"\n'
    )
    cfg = parse_config(text, "points.toml", tmp_path)
    names = [p.name for p in cfg.points]
    assert names[:2] == ["meter.voltage_l1", "meter.voltage_l2"] and "cfw7011.status" in names
    assert {p.interval for p in cfg.points if p.slave == 4} == {0.5}
    meter = cfg.devices[0]
    assert meter.template is not None and meter.template.model == "SDM630"
    assert (
        meter.limits.max_registers == 20 and meter.limits.max_gap == 10
    )  # the device's over the template's
    assert meter.hints["meter.voltage_l1"]["device_class"] == "voltage"
    with pytest.raises(ConfigError) as info:
        parse_config(
            text.replace("meters/sdm630.toml", "meters/sdm120.toml"), "points.toml", tmp_path
        )
    assert str(info.value).startswith("points.toml:8: device[0]: template: ")
    assert "sdm120.toml: no such file" in str(info.value)
    broken = SDM630.read_text().replace('unit = "Hz"', 'unit = "Hz"\ncolour = 1')
    (tmp_path / "meters" / "sdm630.toml").write_text(broken)
    with pytest.raises(ConfigError) as info:
        parse_config(text, "points.toml", tmp_path)
    line = broken.splitlines().index("colour = 1") + 1
    assert f'sdm630.toml:{line}: point[3] ("frequency"): colour: unknown key' in str(info.value)


def test_the_templates_and_the_schema_are_package_data() -> None:
    """Every built-in template and the schema are in the wheel (pyproject's
    package-data) and in the sdist (MANIFEST.in)."""
    import fnmatch

    root = Path(registry.__file__).resolve().parents[2]
    globs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["pyrtu"]
    manifest = (root / "MANIFEST.in").read_text()
    files = [*registry.BUILTIN_DIR.glob("*.toml"), registry.SCHEMA_PATH]
    assert len(files) == 7
    for f in files:
        inside = f.relative_to(root / "pyrtu").as_posix()
        assert any(fnmatch.fnmatch(inside, g) for g in globs), inside
        assert f.name in manifest or f"{f.parent.relative_to(root).as_posix()} *.toml" in manifest
