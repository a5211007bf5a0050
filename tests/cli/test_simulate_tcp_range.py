"""``pyrtu simulate --tcp HOST:FIRST-LAST``: a device of its own on every port of a
range, all served by one process (issue 30, item 3)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import Background, env, free_port_range, pyrtu

from pyrtu import Master

PORTS = 6
TEMPLATE = """\
[device]
vendor = "test"
model = "range"
address = 3

[[point]]
name = "a"
table = "holding"
address = 10
initial = 1234
writable = true

[[point]]
name = "b"
table = "holding"
address = 11
initial = 4321
"""


@pytest.fixture
def template(tmp_path: Path) -> Path:
    path = tmp_path / "range.toml"
    path.write_text(TEMPLATE)
    return path


@pytest.fixture
def served(template: Path) -> Iterator[tuple[Background, int, dict[str, object]]]:
    """``simulate --template --tcp 127.0.0.1:FIRST-LAST --json``: (it, FIRST, its ready line)."""
    for _ in range(5):
        first = free_port_range(PORTS)
        spec = f"127.0.0.1:{first}-{first + PORTS - 1}"
        bg = Background("simulate", "--template", template, "--tcp", spec, "--json")
        try:
            ready = json.loads(bg.line(timeout=60))
        except Exception:
            result = bg.finish()
            if "cannot listen" in result.err:  # a port taken meanwhile: another range
                continue
            raise AssertionError(result.err) from None
        try:
            yield bg, first, ready
        finally:
            bg.kill()
        return
    raise AssertionError("no range of ports could be bound")


def test_every_port_serves_a_device_of_its_own(
    served: tuple[Background, int, dict[str, object]],
) -> None:
    bg, first, ready = served
    assert ready["type"] == "ready" and ready["address"] == 3
    assert ready["tcp"] == f"127.0.0.1:{first}-{first + PORTS - 1}"
    assert ready["tcp_ports"] == PORTS
    urls = [f"tcp://127.0.0.1:{port}" for port in range(first, first + PORTS)]
    with Master(urls[0], timeout=2.0) as one, Master(urls[-1], timeout=2.0) as last:
        # the template's initial values (TEMPLATE) on the first and the last port
        assert one.read_holding_registers(3, 10, 2) == [1234, 4321]
        assert last.read_holding_registers(3, 10, 2) == [1234, 4321]
        one.write_register(3, 10, 7)  # one device's state: the other keeps its own
        assert one.read_holding_registers(3, 10, 1) == [7]
        assert last.read_holding_registers(3, 10, 1) == [1234]
    for url in urls[1:-1]:  # every port of the range answers
        with Master(url, timeout=2.0) as m:
            assert m.read_holding_registers(3, 11, 1) == [4321]
    bg.proc.terminate()
    result = bg.finish()
    assert result.code == 0, result.err
    stopped = result.json_lines()[-1]
    # 5 + PORTS - 2 requests, each answered: the counters of every port added up
    requests = 5 + PORTS - 2
    assert stopped["type"] == "stopped"
    assert stopped["counters"] == {"requests": requests, "responses": requests, "exceptions": 0}


@pytest.mark.parametrize(
    ("spec", "said"),
    [
        ("127.0.0.1:5001-5000", "the range 5001-5000 ends before it starts"),
        ("127.0.0.1:0-10", "a port of a range is 1..65535, not 0"),
        ("127.0.0.1:65535-65536", "a port of a range is 1..65535, not 65536"),
        ("127.0.0.1:20000-30000", "the range 20000-30000 has 10001 ports; at most 10000"),
        ("127.0.0.1:20000-", "expected HOST:PORT or HOST:FIRST-LAST"),
        (":20000-20001", "expected HOST:PORT or HOST:FIRST-LAST"),
        ("127.0.0.1:-5", "expected HOST:PORT or HOST:FIRST-LAST"),
    ],
)
def test_a_bad_range_is_a_usage_error_naming_the_flag(template: Path, spec: str, said: str) -> None:
    result = pyrtu("simulate", "--template", template, "--tcp", spec)
    assert result.code == 2, result.err
    assert "argument --tcp: " + said in result.err
    assert "Traceback" not in result.err


def test_the_largest_range_and_one_port_of_65535_are_accepted() -> None:
    from pyrtu.cli._simulate_tcp import MAX_RANGE, tcp_range

    # the boundaries: 10,000 ports (MAX_RANGE) and the last port, alone and as a range
    assert tcp_range(f"h:1-{MAX_RANGE}") == ("h", 1, MAX_RANGE)
    assert tcp_range("h:65535-65535") == ("h", 65535, 65535)
    assert tcp_range("[::1]:502-503") == ("::1", 502, 503)
    assert tcp_range("h:0") == ("h", 0, 0)  # a single port may be 0: any free port


def test_a_range_takes_no_serial_port(template: Path) -> None:
    result = pyrtu("simulate", "--template", template, "--tcp", "127.0.0.1:20000-20001",
                   "--port", "/dev/null")  # fmt: skip
    assert result.code == 2
    assert "--tcp: a range of ports serves a device of its own on each port" in result.err


def test_a_port_of_the_range_taken_is_a_port_error_naming_it(template: Path) -> None:
    first = free_port_range(4)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", first + 2))
        taken.listen(1)
        result = pyrtu("simulate", "--template", template, "--tcp",
                       f"127.0.0.1:{first}-{first + 3}", "--duration", "30")  # fmt: skip
    assert result.code == 3, result.err
    assert f"cannot listen on 127.0.0.1:{first + 2}" in result.err
    assert "Traceback" not in result.err


def test_too_few_open_files_for_the_range_is_a_usage_error(template: Path) -> None:
    """The hard limit of open files below a socket per port and per client: refused
    before a port is bound, naming --tcp and the limit."""
    limit = "import resource; resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))"
    code = f"{limit}; from pyrtu.cli import main; raise SystemExit(main())"
    done = subprocess.run(
        [sys.executable, "-c", code, "simulate", "--template", str(template),
         "--tcp", "127.0.0.1:20000-20500"],
        capture_output=True, text=True, env=env(), timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "--tcp: 501 ports need 1066 open files" in done.stderr
    assert "at most 256 (ulimit -Hn)" in done.stderr
