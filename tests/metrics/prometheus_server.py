"""A real Prometheus for the metrics tests (Debian's ``prometheus``): started on a
free loopback port with a generated configuration that scrapes the given targets
every 500 ms, queried through its HTTP API (``/api/v1/query``), stopped by pid.

    with Prometheus(tmp_path, ["127.0.0.1:9101"]) as prom:
        prom.wait("pyrtu_poll_transactions_total", lambda v: v >= 10, "transactions")

Whatever Prometheus the system may run as a service is not used: this one has
its own port, configuration and storage under the test's directory.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.parse
import urllib.request
from collections.abc import Callable
from pathlib import Path
from types import TracebackType

import pytest

PROMETHEUS = shutil.which("prometheus") or "/usr/bin/prometheus"
#: the scrape interval (Prometheus accepts milliseconds)
INTERVAL = "500ms"
#: a safety net for conditions awaited, not a measurement
PATIENCE = 30.0


def need_prometheus() -> None:
    if not os.path.exists(PROMETHEUS):
        if os.environ.get("CI"):
            pytest.fail("prometheus is not installed (make system-packages installs it)")
        pytest.skip("prometheus is not installed (apt-get install prometheus)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Prometheus:
    """One prometheus process scraping ``targets`` (HOST:PORT each)."""

    def __init__(self, directory: Path, targets: list[str]) -> None:
        need_prometheus()
        self.dir = Path(directory) / f"prometheus-{id(self):x}"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.conf = self.dir / "prometheus.yml"
        self.conf.write_text(
            "global:\n"
            f"  scrape_interval: {INTERVAL}\n"
            f"  scrape_timeout: {INTERVAL}\n"
            "scrape_configs:\n"
            "  - job_name: pyrtu\n"
            "    static_configs:\n"
            f"      - targets: {json.dumps(targets)}\n"
        )
        self.log = self.dir / "prometheus.log"
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> Prometheus:
        err = open(self.log, "ab")
        # a tool, not the code under test: no sanitizer preloaded into it (make test-asan)
        tool_env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "ASAN_OPTIONS")}
        self.proc = subprocess.Popen(
            [
                PROMETHEUS,
                f"--config.file={self.conf}",
                f"--web.listen-address=127.0.0.1:{self.port}",
                f"--storage.tsdb.path={self.dir / 'data'}",
                "--log.level=warn",
            ],
            stdout=err,
            stderr=err,
            env=tool_env,
        )
        err.close()
        give_up = time.monotonic() + PATIENCE
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"prometheus exited {self.proc.returncode}: {self.logs()}")
            try:
                with urllib.request.urlopen(f"{self.url}/-/ready", timeout=1) as answer:
                    if answer.status == 200:
                        return self
            except OSError:
                pass
            if time.monotonic() > give_up:
                self.stop()
                raise RuntimeError(f"prometheus was not ready: {self.logs()}")
            time.sleep(0.05)

    def logs(self) -> str:
        return self.log.read_text(errors="replace")[-2000:]

    def query(self, expression: str) -> list[tuple[dict[str, str], float]]:
        """The instant vector of ``expression`` now: (labels, value) per series."""
        url = f"{self.url}/api/v1/query?" + urllib.parse.urlencode({"query": expression})
        with urllib.request.urlopen(url, timeout=5) as answer:
            doc = json.load(answer)
        assert doc["status"] == "success", doc
        return [(r["metric"], float(r["value"][1])) for r in doc["data"]["result"]]

    def value(self, expression: str) -> float | None:
        """The one value of ``expression`` (None: no series yet)."""
        found = self.query(expression)
        assert len(found) <= 1, (expression, found)
        return found[0][1] if found else None

    def wait(self, expression: str, condition: Callable[[float], bool], what: str) -> float:
        """Until ``expression``'s one value meets ``condition``; that value."""
        give_up = time.monotonic() + PATIENCE
        while True:
            value = self.value(expression)
            if value is not None and condition(value):
                return value
            assert time.monotonic() < give_up, f"gave up waiting for {what}: {expression} = {value}"
            time.sleep(0.1)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)

    def __enter__(self) -> Prometheus:
        return self.start()

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()
