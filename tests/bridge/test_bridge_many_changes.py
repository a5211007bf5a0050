"""Every change published: the short version of bench/bench_many_bridge.py (issue 30).
Twenty Modbus TCP devices of thirty registers, one ``pyrtu simulate --tcp
127.0.0.1:FIRST-LAST --vary`` process whose registers step one count every
half second, polled by ``pyrtu bridge`` five times a step (each its own process),
into a real mosquitto; a subscriber of this test's own sees every step of every
register published once, in order."""

from __future__ import annotations

import contextlib
import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

from cli_helpers import Background, free_port_range
from mqtt_broker import Broker, Client

DEVICES = 20
REGISTERS = 30
STEP = 0.5  # the simulator's --vary
POLL = 0.1  # the bridge's interval: five polls a step


def template_text() -> str:
    lines = ["[device]", 'vendor = "test"', 'model = "many"', "address = 1", ""]
    for r in range(REGISTERS):
        lines += ["[[point]]", f'name = "r{r}"', 'table = "holding"', f"address = {r}",
                  f"initial = {r * 100}", ""]  # fmt: skip
    return "\n".join(lines)


def bridge_text(url: str, outbox: Path, first: int, messages: str = "point") -> str:
    """The bridge's configuration: a ``tcp://`` bus per device, every register a point
    (``messages``: the ``[mqtt]`` key)."""
    out = [f'[mqtt]\nurl = "{url}"\nedge = "many"\noutbox = "{outbox}"\n'
           f'messages = "{messages}"\n',
           f'[defaults]\ninterval = {POLL}\ntable = "holding"\nslave = 1\n']  # fmt: skip
    for i in range(DEVICES):
        out.append(f'[[bus]]\nname = "d{i}"\nport = "tcp://127.0.0.1:{first + i}"\n')
        out += [
            f'[[point]]\nname = "d{i}.r{r}"\nbus = "d{i}"\naddress = {r}\n'
            for r in range(REGISTERS)
        ]
    return "\n".join(out)


@contextlib.contextmanager
def simulated(tmp_path: Path) -> Iterator[int]:
    """The devices: one ``pyrtu simulate --tcp`` range whose registers step every
    `STEP`, answering; its first port (killed at the end)."""
    template = tmp_path / "many.toml"
    template.write_text(template_text())
    first = free_port_range(DEVICES)
    spec = f"127.0.0.1:{first}-{first + DEVICES - 1}"
    sim = Background("simulate", "--template", template, "--tcp", spec, "--vary", str(STEP),
                     "--json")  # fmt: skip
    try:
        json.loads(sim.line(timeout=60))
        yield first
    finally:
        sim.kill()


def test_every_step_of_every_register_is_published_once_in_order(tmp_path: Path) -> None:
    with simulated(tmp_path) as first:
        with Broker(tmp_path) as broker, Client(broker, ["pyrtu/many/+/1/+"]) as sub:
            config = tmp_path / "bridge.toml"
            config.write_text(bridge_text(broker.url, tmp_path / "outbox", first))
            bridge = Background("bridge", "--config", config)
            try:
                points = DEVICES * REGISTERS

                def values() -> dict[str, list[int]]:
                    got: dict[str, list[int]] = {}
                    for topic, body, _retain, _props, _t in list(sub.messages):
                        if body.startswith(b"{"):
                            got.setdefault(topic, []).append(json.loads(body)["value"])
                    return got

                def started() -> bool:
                    assert bridge.proc.poll() is None, "".join(bridge.err)
                    return len(values()) == points

                sub.wait(started, "a value of every point", 60)
                time.sleep(8 * STEP)
                bridge.proc.send_signal(signal.SIGTERM)
                assert bridge.finish(30).code == 0
            finally:
                bridge.kill()
        got = values()
        assert len(got) == points
        for i in range(DEVICES):
            for r in range(REGISTERS):
                seq = got[f"pyrtu/many/d{i}/1/d{i}.r{r}"]
                # one step a value: consecutive counts from the first one published (no
                # change left out, none published twice); every point stepped 6 times
                assert seq == list(range(seq[0], seq[0] + len(seq))), (i, r, seq)
                assert len(seq) >= 7, (i, r, seq)
        # the same step on every device: the registers' initial values r * 100 apart
        lasts = {got[f"pyrtu/many/d{i}/1/d{i}.r{r}"][-1] - r * 100 for i in range(DEVICES)
                 for r in range(REGISTERS)}  # fmt: skip
        assert max(lasts) - min(lasts) <= 1, lasts
