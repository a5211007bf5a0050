"""``pyrtu simulate --template FILE --vary SECONDS``: the measured values of a
template's device change every SECONDS (issue 30), read back by pyrtu's `Master`
over Modbus TCP from the real command."""

from __future__ import annotations

import itertools
import json
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import Background, free_port_range, pyrtu

from pyrtu import Master

PERIOD = 0.4
#: a measured counter "a" (initial 5), a writable "w", a measured "small" within
#: 0..2 (initial 1), a scaled measured input register "t" (raw 200 = 20.0) and a
#: measured discrete input "on" (initial false)
TEMPLATE = """\
[device]
vendor = "test"
model = "vary"
address = 1

[[point]]
name = "a"
table = "holding"
address = 0
initial = 5

[[point]]
name = "w"
table = "holding"
address = 1
initial = 9
writable = true

[[point]]
name = "small"
table = "holding"
address = 2
initial = 1
min = 0
max = 2

[[point]]
name = "t"
table = "input"
address = 0
type = "int16"
scale = 0.1
initial = 20.0

[[point]]
name = "on"
table = "discrete_inputs"
address = 0
"""


@pytest.fixture
def template(tmp_path: Path) -> Path:
    path = tmp_path / "vary.toml"
    path.write_text(TEMPLATE)
    return path


@pytest.fixture
def one(template: Path) -> Iterator[tuple[Background, int]]:
    """One device on a free port (--tcp 127.0.0.1:0), stepping every PERIOD."""
    bg = Background("simulate", "--template", template, "--tcp", "127.0.0.1:0",
                    "--vary", str(PERIOD), "--json")  # fmt: skip
    try:
        ready = json.loads(bg.line(timeout=60))
        yield bg, int(str(ready["tcp"]).rsplit(":", 1)[1])
    finally:
        bg.kill()


@pytest.mark.wall_clock
def test_each_measured_value_takes_the_next_step_of_its_ramp_every_period(
    one: tuple[Background, int],
) -> None:
    bg, port = one
    seen: list[tuple[float, list[int]]] = []  # (time, [a, w, small]) at each change of a
    exact = 0  # reads of "t" and "on" between two reads of one step
    with Master(f"tcp://127.0.0.1:{port}", timeout=2.0) as m:
        end = time.monotonic() + 6 * PERIOD
        while time.monotonic() < end:
            a, w, small = m.read_holding_registers(1, 0, 3)
            now = time.monotonic()
            k = a - 5  # the step: "a" counts from its initial value
            assert w == 9  # a client's to write: never varied
            assert small == (1 + k) % 3  # 1, 2, 0, 1...: within min..max, wrapping
            t_raw = m.read_input_registers(1, 0, 1)[0]
            on = m.read_discrete_inputs(1, 0, 1)[0]
            if m.read_holding_registers(1, 0, 1)[0] == a:  # still step k
                exact += 1
                assert t_raw == 200 + k  # 20.0, 20.1...: one count of scale 0.1
                assert on is (k % 2 == 1)  # a bool toggles
            if not seen or seen[-1][1][0] != a:
                seen.append((now, [a, w, small]))
            time.sleep(0.01)
        # a write to the writable point stays while the others step
        m.write_register(1, 1, 77)
        time.sleep(2 * PERIOD)
        assert m.read_holding_registers(1, 1, 1) == [77]
    steps = [v[0] for _, v in seen]
    assert steps == list(range(steps[0], steps[0] + len(steps))), steps  # one count a step
    assert len(steps) >= 5, steps
    assert exact >= 20, exact
    # between the changes seen (the first read is no change): one period each
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(seen[1:])]
    assert all(abs(g - PERIOD) < 0.12 for g in gaps), gaps
    bg.proc.terminate()
    assert bg.finish().code == 0


def test_every_device_of_a_range_steps_at_the_same_instants(template: Path) -> None:
    first = free_port_range(3)
    bg = Background("simulate", "--template", template, "--tcp",
                    f"127.0.0.1:{first}-{first + 2}", "--vary", "0.5", "--json")  # fmt: skip
    try:
        json.loads(bg.line(timeout=60))
        with (
            Master(f"tcp://127.0.0.1:{first}", timeout=2.0) as m0,
            Master(f"tcp://127.0.0.1:{first + 2}", timeout=2.0) as m2,
        ):
            m0.write_register(1, 1, 1000)  # one device's writable point: its own
            begin = m0.read_holding_registers(1, 0, 1)[0]
            for _ in range(8):
                a0 = m0.read_holding_registers(1, 0, 1)[0]
                a2 = m2.read_holding_registers(1, 0, 1)[0]
                assert a2 - a0 in (0, 1)  # the same step, or the next one
                time.sleep(0.15)
            assert m0.read_holding_registers(1, 0, 1)[0] >= begin + 2  # it stepped
            assert m0.read_holding_registers(1, 1, 1) == [1000]
            assert m2.read_holding_registers(1, 1, 1) == [9]
        bg.proc.terminate()
        assert bg.finish().code == 0
    finally:
        bg.kill()


def test_the_smallest_time_is_accepted_and_steps_at_every_read(template: Path) -> None:
    """1 µs: above 0, the flag's boundary; every read is on a step of its own."""
    bg = Background("simulate", "--template", template, "--tcp", "127.0.0.1:0",
                    "--vary", "1us", "--json")  # fmt: skip
    try:
        port = int(str(json.loads(bg.line(timeout=60))["tcp"]).rsplit(":", 1)[1])
        with Master(f"tcp://127.0.0.1:{port}", timeout=2.0) as m:
            reads = [m.read_holding_registers(1, 0, 1)[0] for _ in range(3)]
        assert len(set(reads)) == 3, reads
        bg.proc.terminate()
        assert bg.finish().code == 0
    finally:
        bg.kill()


@pytest.mark.parametrize("given", ["0", "0us", "-1", "nan", "inf", "abc", ""])
def test_a_time_not_above_zero_is_a_usage_error_before_any_port_opens(
    template: Path, given: str
) -> None:
    with socket.socket() as held:  # its port taken: opening it first would be exit 3
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        result = pyrtu("simulate", "--template", template, "--tcp", f"127.0.0.1:{port}",
                       "--vary", given)  # fmt: skip
    assert result.code == 2, result.err
    assert "argument --vary: " in result.err
    assert "Traceback" not in result.err


def test_a_drive_simulator_computes_its_values_itself() -> None:
    result = pyrtu("simulate", "cfw100", "--tcp", "127.0.0.1:0", "--vary", "1")
    assert result.code == 2, result.err
    assert "--vary: the cfw100 simulator computes its values" in result.err
    assert "Traceback" not in result.err


#: every kind of point in holding registers 0..8, read in one request: a counter
#: "a" (the step), an enum, a 3-bit field beside a writable bit, a measured high
#: byte beside a writable low byte, a float32 within 1.5..3.5, a writable register
#: and its measured alias, a string
KINDS = """\
[device]
vendor = "test"
model = "kinds"
address = 1

[[point]]
name = "a"
table = "holding"
address = 0

[[point]]
name = "mode"
table = "holding"
address = 1
enum = { 0 = "off", 1 = "run", 5 = "fault" }
initial = "run"

[[point]]
name = "low3"
table = "holding"
address = 2
bits = [0, 3]
initial = 6

[[point]]
name = "flag"
table = "holding"
address = 2
bit = 8
writable = true
initial = true

[[point]]
name = "hi"
table = "holding"
address = 3
type = "uint8"
order = "high"
initial = 10

[[point]]
name = "lo"
table = "holding"
address = 3
type = "uint8"
order = "low"
writable = true
initial = 7

[[point]]
name = "f"
table = "holding"
address = 4
type = "float32"
min = 1.5
max = 3.5
initial = 2.0

[[point]]
name = "w"
table = "holding"
address = 6
writable = true
initial = 9

[[point]]
name = "w_alias"
table = "holding"
address = 6

[[point]]
name = "name"
table = "holding"
address = 7
type = "string"
count = 2
initial = "ab"
"""


def test_each_kind_of_point_steps_as_documented(tmp_path: Path) -> None:
    template = tmp_path / "kinds.toml"
    template.write_text(KINDS)
    bg = Background("simulate", "--template", template, "--tcp", "127.0.0.1:0",
                    "--vary", "0.2", "--json")  # fmt: skip
    try:
        port = int(str(json.loads(bg.line(timeout=60))["tcp"]).rsplit(":", 1)[1])
        steps = set()
        with Master(f"tcp://127.0.0.1:{port}", timeout=2.0) as m:
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                r = m.read_holding_registers(1, 0, 9)
                k = r[0]  # the counter: 0, 1, 2...
                steps.add(k)
                assert r[1] == (0, 1, 5)[(1 + k) % 3]  # run, fault, off, run...
                assert r[2] & 0x7 == (6 + k) % 8  # the field: 6, 7, 0, 1...
                assert r[2] >> 3 == 0x100 >> 3  # the writable bit kept, nothing else
                assert r[3] == ((10 + k) % 256) << 8 | 7  # its byte steps, the other's kept
                f = struct.unpack(">f", struct.pack(">HH", r[4], r[5]))[0]
                assert f == (2.0, 3.0)[k % 2]  # whole numbers within 1.5..3.5
                assert r[6] == 9  # a writable register: its measured alias does not step
                assert r[7:9] == [ord("a") << 8 | ord("b"), 0]  # a string keeps its value
                time.sleep(0.02)
        assert len(steps) >= 6, steps
        bg.proc.terminate()
        assert bg.finish().code == 0
    finally:
        bg.kill()
