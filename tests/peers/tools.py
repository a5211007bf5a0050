"""Interoperability peers: build them, run them, talk to them.

The pytest fixtures are in `peers.fixtures`; this module has the plain helpers:

* `build_peers`: compiles ``libmodbus_server.c`` and ``libmodbus_client.c`` with
  ``gcc -Wall -Wextra -Werror $(pkg-config --cflags --libs libmodbus)``.
* `Peer`: a peer program in a subprocess, started, awaited (``READY`` on its
  stdout) and stopped with SIGTERM (its last ``STATS`` line is kept).
* `libmodbus_server`, `pymodbus_server`, `pyrtu_slave_process`: the three slaves.
* `libmodbus_script`, `libmodbus_bench`: the libmodbus client.
* `socat_pair`: two pseudo-terminals joined by socat (``pty,raw,echo=0``).
* `pymodbus_client`, `minimal_instrument`: the Python clients, opened 8N1.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

PEERS = Path(__file__).resolve().parent
REPO = PEERS.parent.parent
CFLAGS = ("-O2", "-Wall", "-Wextra", "-Werror")


def peer_env() -> dict[str, str]:
    """The environment of Python peers: pyrtu importable from this checkout."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


# -- building the C peers --------------------------------------------------------


class PeerBuildError(RuntimeError):
    """The libmodbus peers cannot be built here."""


@dataclass(frozen=True)
class PeerBinaries:
    server: Path
    client: Path
    libmodbus_version: str


def build_peers(directory: Path) -> PeerBinaries:
    """Compile the libmodbus peers into `directory`."""
    gcc = shutil.which("gcc") or shutil.which("cc")
    pkg_config = shutil.which("pkg-config")
    hint = "install it with: apt-get install -y libmodbus-dev pkg-config gcc"
    if gcc is None or pkg_config is None:
        raise PeerBuildError(f"the libmodbus peers need gcc and pkg-config ({hint})")
    probe = subprocess.run(
        [pkg_config, "--modversion", "libmodbus"], capture_output=True, text=True, check=False
    )
    if probe.returncode != 0:
        raise PeerBuildError(
            "libmodbus-dev is missing (pkg-config cannot find libmodbus): the interop "
            f"tests need the libmodbus peers; {hint}"
        )
    flags = subprocess.run(
        [pkg_config, "--cflags", "--libs", "libmodbus"], capture_output=True, text=True, check=True
    ).stdout.split()
    out = {}
    for name in ("server", "client"):
        source = PEERS / f"libmodbus_{name}.c"
        binary = directory / f"libmodbus_{name}"
        cmd = [gcc, *CFLAGS, "-o", str(binary), str(source), *flags]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise PeerBuildError(
                f"compiling {source.name} failed:\n$ {shlex.join(cmd)}\n{done.stderr}"
            )
        out[name] = binary
    return PeerBinaries(out["server"], out["client"], probe.stdout.strip())


# -- running peers ---------------------------------------------------------------


class PeerError(RuntimeError):
    """A peer did not start, or died."""


class Peer:
    """A peer program in a subprocess (context manager).

    Started by `start` (or ``with``): waits for the ``READY`` line on stdout.
    `stop` sends SIGTERM, waits, and returns the ``STATS`` line (or ``""``).
    stderr goes to a log file whose tail error messages quote.
    """

    def __init__(
        self, name: str, argv: Sequence[str | Path], *, ready_timeout: float = 15.0
    ) -> None:
        self.name = name
        self.argv = [str(a) for a in argv]
        self.ready_timeout = ready_timeout
        self.proc: subprocess.Popen[str] | None = None
        self.ready_line = ""
        self.stats = ""
        self._log: IO[str] | None = None

    def __enter__(self) -> Peer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def log_tail(self, lines: int = 20) -> str:
        if self._log is None:
            return ""
        self._log.flush()
        with open(self._log.name, encoding="utf-8", errors="replace") as f:
            return "".join(f.readlines()[-lines:])

    def start(self) -> Peer:
        self._log = tempfile.NamedTemporaryFile(
            "w+", prefix=f"pyrtu-peer-{self.name}-", suffix=".log", delete=False
        )
        self.proc = subprocess.Popen(
            self.argv,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=peer_env(),
            start_new_session=True,  # a Ctrl-C of the test run does not reach it twice
        )
        assert self.proc.stdout is not None
        deadline = time.monotonic() + self.ready_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.stop()
                raise PeerError(f"{self.name} did not start in {self.ready_timeout} s")
            ready, _, _ = select.select([self.proc.stdout], [], [], left)
            if ready:
                line = self.proc.stdout.readline()
                if line.startswith("READY"):
                    self.ready_line = line.strip()
                    return self
                if not line:  # EOF: it died
                    self.proc.wait()
                    tail = self.log_tail()
                    self.stop()
                    raise PeerError(
                        f"{self.name} exited with {self.proc.returncode} before READY:\n"
                        f"$ {shlex.join(self.argv)}\n{tail}"
                    )

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def cpu_seconds(self) -> float:
        """User + system CPU time of the peer so far (from /proc, 10 ms resolution)."""
        with open(f"/proc/{self.pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> str:
        proc, self.proc = self.proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                out, _ = proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
            for line in out.splitlines():
                if line.startswith("STATS"):
                    self.stats = line[5:].strip()
        if self._log is not None:
            self._log.close()
            with contextlib.suppress(OSError):
                os.unlink(self._log.name)
            self._log = None
        return self.stats


def libmodbus_server(
    binaries: PeerBinaries,
    port: str,
    slave: int,
    *,
    baudrate: int = 115200,
    args: Sequence[str] = (),
) -> Peer:
    """The libmodbus server on `port` (not started: use ``with``)."""
    return Peer(
        f"libmodbus-server-{slave}",
        [binaries.server, port, str(slave), "--baud", str(baudrate), *args],
    )


def pymodbus_server(port: str, slave: int, *, baudrate: int = 115200, mode: str = "rtu") -> Peer:
    """The pymodbus server on `port`, RTU, ASCII, TCP or UDP (``mode="tcp"`` or
    ``"udp"``, `port` is HOST:PORT) (not started: use ``with``)."""
    argv: list[str | Path] = [sys.executable, PEERS / "pymodbus_server.py", port, str(slave)]
    argv += ["--baud", str(baudrate), *(["--ascii"] if mode == "ascii" else [])]
    argv += [f"--{mode}"] if mode in ("tcp", "udp") else []
    return Peer(f"pymodbus-server-{slave}", argv)


def pyrtu_slave_process(
    port: str, slave: int, *, baudrate: int = 115200, t35: float | None = None
) -> Peer:
    """A pyrtu Slave in its own process on `port` (not started: use ``with``)."""
    argv: list[str | Path] = [
        sys.executable,
        PEERS / "pyrtu_slave.py",
        port,
        str(slave),
        "--baud",
        str(baudrate),
    ]
    if t35 is not None:
        argv += ["--t35", repr(t35)]
    return Peer(f"pyrtu-slave-{slave}", [str(a) for a in argv])


def libmodbus_script(
    binaries: PeerBinaries,
    port: str,
    slave: int,
    ops: Sequence[str],
    *,
    baudrate: int = 115200,
    timeout_ms: int = 500,
) -> list[dict[str, Any]]:
    """Run the libmodbus client's OPs (see libmodbus_client.c); one dict per OP."""
    cmd = [
        str(binaries.client),
        port,
        str(slave),
        "--baud",
        str(baudrate),
        "--timeout-ms",
        str(timeout_ms),
        "script",
        *ops,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    if done.returncode != 0:
        raise PeerError(f"$ {shlex.join(cmd)}\nexit {done.returncode}\n{done.stderr}")
    results = [json.loads(line) for line in done.stdout.splitlines()]
    assert [r["op"] for r in results] == list(ops), done.stdout
    return results


def libmodbus_bench(
    binaries: PeerBinaries,
    port: str,
    slave: int,
    transactions: int,
    *,
    address: int = 0,
    baudrate: int = 115200,
    warmup: int = 50,
) -> dict[str, Any]:
    """N FC 03 transactions of 10 registers by the libmodbus client; its JSON report."""
    cmd = [
        str(binaries.client),
        port,
        str(slave),
        "--baud",
        str(baudrate),
        "--warmup",
        str(warmup),
        "bench",
        str(transactions),
        str(address),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    if not done.stdout.strip():
        raise PeerError(f"$ {shlex.join(cmd)}\nexit {done.returncode}\n{done.stderr}")
    report: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return report


# -- pseudo-terminal pair --------------------------------------------------------


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def socat_pair() -> Iterator[tuple[str, str]]:
    """Two pseudo-terminals joined by socat (``pty,raw,echo=0`` both sides)."""
    socat = shutil.which("socat")
    if socat is None:
        raise PeerBuildError("socat is missing: apt-get install -y socat")
    directory = tempfile.mkdtemp(prefix="pyrtu-socat-")
    a, b = os.path.join(directory, "a"), os.path.join(directory, "b")
    proc = subprocess.Popen(
        [socat, f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 10
        while not (os.path.exists(a) and os.path.exists(b)):
            if proc.poll() is not None or time.monotonic() > deadline:
                err = proc.stderr.read() if proc.stderr else ""
                raise PeerError(f"socat did not create the pty pair: {err}")
            time.sleep(0.01)
        yield a, b
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(directory, ignore_errors=True)


@contextlib.contextmanager
def socat_pty_over_tcp(link: Path) -> Iterator[int]:
    """A device server as an RTU-over-TCP gateway is one: socat opens a pseudo-terminal
    at ``link`` (``raw,echo=0``), then listens on a free loopback port (yielded) and
    joins its first connection to the pty."""
    port = free_tcp_port()
    proc = subprocess.Popen(
        ["socat", f"PTY,link={link},raw,echo=0", f"TCP-LISTEN:{port},bind=127.0.0.1,reuseaddr"],
        stderr=subprocess.DEVNULL,
    )
    for _ in range(200):
        if link.exists():
            break
        time.sleep(0.01)
    try:
        yield port
    finally:
        proc.terminate()
        proc.wait(5)


# -- Python clients ----------------------------------------------------------------


def pymodbus_client(
    port: str, *, baudrate: int = 115200, timeout: float = 1.0, mode: str = "rtu"
) -> Any:
    """A connected pymodbus 3.x ModbusSerialClient (RTU or ASCII, 8N1)."""
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    client = ModbusSerialClient(
        port,
        framer=FramerType.ASCII if mode == "ascii" else FramerType.RTU,
        baudrate=baudrate,
        bytesize=8,
        parity="N",
        stopbits=1,
        timeout=timeout,
        retries=0,
    )
    if not client.connect():
        raise PeerError(f"pymodbus cannot open {port}")
    return client


def minimal_instrument(
    port: str, slave: int, *, baudrate: int = 115200, timeout: float = 1.0, mode: str = "rtu"
) -> Any:
    """A minimalmodbus Instrument (RTU or ASCII, 8N1) on `port`."""
    import minimalmodbus
    import serial

    inst = minimalmodbus.Instrument(
        port, slave, mode=minimalmodbus.MODE_ASCII if mode == "ascii" else minimalmodbus.MODE_RTU
    )
    inst.serial.baudrate = baudrate
    inst.serial.bytesize = 8
    inst.serial.parity = serial.PARITY_NONE
    inst.serial.stopbits = 1
    inst.serial.timeout = timeout
    return inst
