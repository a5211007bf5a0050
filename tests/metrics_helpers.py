"""Helpers of the ``--metrics`` tests: a command's endpoint scraped directly (the
exposition parsed by prometheus_client's own parser), its health, the poller's
configuration on a virtual bus, waiting for a condition."""

from __future__ import annotations

import json
import signal
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cli_helpers import Background, poll_weg
from prometheus_client.parser import text_string_to_metric_families

#: a safety net for conditions awaited, never a measurement
PATIENCE = 30.0
BAUD = 115200
#: the serial options of the commands under test (the virtual bus needs N)
SERIAL = ("--baudrate", str(BAUD), "--parity", "N")


def next_json(bg: Background, kind: str) -> dict[str, Any]:
    """The next JSON line of ``bg``'s output whose ``type`` is ``kind``."""
    while True:
        doc: dict[str, Any] = json.loads(bg.line(timeout=20))
        if doc.get("type") == kind:
            return doc


def stop(bg: Background) -> int:
    """Ctrl-C to ``bg``; its exit status."""
    bg.proc.send_signal(signal.SIGINT)
    return bg.finish().code


POLL_CONFIG = poll_weg(0.05, "offline_after = 2\n")


def write_poll_config(directory: Path, port: str) -> Path:
    path = directory / "points.toml"
    path.write_text(POLL_CONFIG.format(port=port))
    return path


def get(url: str) -> tuple[int, str]:
    """The status and body of a GET (an HTTP error status too)."""
    try:
        with urllib.request.urlopen(url, timeout=10) as answer:
            return answer.status, answer.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.read().decode()


def samples(address: str) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    """Every sample of ``http://address/metrics``: (name, labels) -> value."""
    status, body = get(f"http://{address}/metrics")
    assert status == 200, body
    out = {}
    for family in text_string_to_metric_families(body):
        for sample in family.samples:
            out[(sample.name, frozenset(sample.labels.items()))] = sample.value
    return out


def sample(address: str, name: str, **labels: str) -> float | None:
    return samples(address).get((name, frozenset(labels.items())))


def until(condition: Callable[[], bool], what: str, patience: float = PATIENCE) -> None:
    give_up = time.monotonic() + patience
    while not condition():
        assert time.monotonic() < give_up, f"gave up waiting for {what}"
        time.sleep(0.05)


def serving(address: str) -> bool:
    """Whether the endpoint answers (200 on /metrics: the command runs)."""
    try:
        return get(f"http://{address}/metrics")[0] == 200
    except OSError:
        return False


def health(address: str) -> tuple[int, str]:
    return get(f"http://{address}/healthz")
