"""The pieces of configuration the bridge's and the Sparkplug edge node's tests
share (their ``[mqtt]`` table, the bus "line" with the CFW701 "weg" at 1) and the
simulated drives they poll on a virtual bus."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from pyrtu.devices import CFW701Simulator, CV100Simulator, DriveSimulator

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200
#: a bus's lines for its outages: offline after two missed polls, polled again
#: after 0.1 s, then at most every 0.4 s
OUTAGE = "offline_after = 2\nbackoff = 0.1\nmax_backoff = 0.4\n"


def mqtt_table(url: str, outbox: Path, more: str = "", edge: str = "e1") -> str:
    """The ``[mqtt]`` table of the broker at ``url`` (``more``: its other lines),
    reconnecting after 0.1 s, then at most every 0.5 s."""
    return f"""[mqtt]
url = "{url}"
edge = "{edge}"
outbox = "{outbox}"
backoff = 0.1
max_backoff = 0.5
{more}"""


def weg_on_line(port: str, interval: float, bus: str = "", timeout: float = 0.1) -> str:
    """The bus "line" on ``port`` (``bus``: more lines of its table) with the
    CFW701 "weg" at 1 polled every ``interval``."""
    return f"""[[bus]]
name = "line"
port = "{port}"
baudrate = {BAUD}
parity = "N"
timeout = {timeout}
{bus}[[device]]
bus = "line"
slave = 1
profile = "cfw701"
name = "weg"
interval = {interval}
"""


@contextlib.contextmanager
def drives() -> Iterator[tuple[vbus.VirtualBus, list[DriveSimulator]]]:
    """Drop 0: the bridge (or edge node); drop 1: a CFW701 at 1; drop 2: a CV100 at 5."""
    with vbus.VirtualBus(3, baudrate=BAUD, parity="N") as bus:
        sims: list[DriveSimulator] = [CFW701Simulator(), CV100Simulator()]
        for drop, (sim, addr) in enumerate(zip(sims, (1, 5), strict=True), start=1):
            sim.serve(bus.paths[drop], addr, baudrate=BAUD, parity="N")
        try:
            yield bus, sims
        finally:
            for sim in sims:
                with contextlib.suppress(Exception):
                    sim.close()
