"""The C core without its POSIX I/O, as Windows builds it (#32.1).

pyrtu/core/_build_core.py compiles csrc/rtu_*_io.c (the master's exchange thread, the
virtual bus's I/O loop: ppoll, pthreads, termios) only where the platform is POSIX, and
leaves out their declarations elsewhere; the C backend's ``POSIX_IO`` is then False and
the twin's exchange and the Python hub loop take over, while CRC, framers and parsers
stay in C.  ``PYRTU_POSIX_IO=0`` builds that set here, so the Windows composition runs on
this machine end to end (`pyrtu demo`: a master on a pseudo-terminal, the virtual bus).
`make cross-windows` compiles the same files with mingw-w64 (CI).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from c_core import build_variant, missing

ROOT = Path(__file__).resolve().parents[2]
CSRC = ROOT / "csrc"

#: headers of POSIX (not of ISO C99, which Windows toolchains have)
POSIX_HEADERS = re.compile(
    r"^\s*#\s*include\s*<(unistd|termios|poll|pthread|fcntl|signal|dlfcn|sched|sys/[\w/]+)\.h>",
    re.M,
)


def test_posix_headers_only_in_the_io_files() -> None:
    """The naming rule the build and `make cross-windows` use (a name ending in _io.c)
    is the truth: exactly those files of csrc/ include POSIX headers."""
    posix = {p.name for p in CSRC.glob("*.[ch]") if POSIX_HEADERS.search(p.read_text())}
    named = {p.name for p in CSRC.glob("*.c") if p.name.endswith("_io.c")}
    assert (
        posix
        == named
        == {
            "rtu_vbus_io.c",
            "rtu_xfer_io.c",
            "rtu_tcp_io.c",
            "rtu_tls_io.c",
            "rtu_mux_io.c",
            "rtu_serve_io.c",
            "rtu_clock_io.c",
        }
    )


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    env.pop("PYTHONPATH", None)
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def windows_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pyrtu with a C core built as on Windows (PYRTU_POSIX_IO=0): a directory for
    PYTHONPATH holding the package and the two extensions."""
    cc = shutil.which(os.environ.get("CC", "cc"))
    if cc is None:
        missing("no C compiler here")
    return build_variant(tmp_path_factory.mktemp("portable"), 600, PYRTU_POSIX_IO="0")


PROBE = r"""
import pyrtu, pyrtu.core._cext as cext
from pyrtu.drivers import _pyxfer, xfer_runners
from pyrtu.vbus import _cvbus

assert pyrtu.__file__.startswith(__import__("sys").argv[1]), pyrtu.__file__
assert pyrtu.BACKEND == "c" and cext.POSIX_IO is False
for name in ("rtu_xfer_io_run", "rtu_xfer_worker_start", "rtu_vbus_io_run", "rtu_vbus_io_init",
             "rtu_tcp_xfer_run", "rtu_tcp_xfer_call", "rtu_tls_ctx_new", "rtu_tls_handshake"):
    assert not hasattr(cext.lib, name), name
assert xfer_runners._impl(cext) is _pyxfer
assert _cvbus.available is False
from pyrtu.core import _tls
assert not _tls.available(cext)  # (mbaps:// over Python's ssl module)
assert cext.CRCFAST is not None and pyrtu.crc16(b"123456789") == 0x4B37
(frame,) = pyrtu.parse_stream(b"\x01\x03\x00\x00\x00\x0a\xc5\xcd", role="slave")
assert (frame.address, frame.function) == (1, 3), frame
print("ok")
"""


def test_windows_set_leaves_out_the_posix_io(windows_set: Path, tmp_path: Path) -> None:
    env = _env(PYTHONPATH=str(windows_set), PYRTU_REQUIRE_C="1")
    cmd = [sys.executable, "-c", PROBE, str(windows_set)]
    out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


def test_windows_set_runs_the_demo_on_the_twin_io(windows_set: Path, tmp_path: Path) -> None:
    """A master on a pseudo-terminal and the virtual bus, with the core's CRC and
    framers in C and the exchange and hub loop of the twin: the demo's whole run."""
    env = _env(PYTHONPATH=str(windows_set), PYRTU_REQUIRE_C="1")
    cmd = [sys.executable, "-m", "pyrtu", "demo", "--duration", "3", "--plain"]
    out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "demo (backend c)" in out.stdout
    # every drive identified, the CFW701 started (written) and read back running
    for slave in (1, 2, 3, 5):
        assert f"  slave {slave}: " in out.stdout, out.stdout[-2000:]
    assert "P680 0x1700 running" in out.stdout, out.stdout[-2000:]
