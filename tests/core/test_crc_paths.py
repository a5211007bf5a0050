"""Every C CRC path at every length 0..1100 and 8 alignments (tests/core/csrc/crc_paths.c).

The SIMD folding functions hand short messages to the slicing code (below 48 / 64
bytes); built a second time with the thresholds lowered to the least the folding
code accepts, the same program exercises the folding code at every length, as the
comment in csrc/rtu_crc.c promises.  Compiled with ASan/UBSan when the compiler
has them, so that a read past the message or NULL + 0 arithmetic fails the test.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LOWERED = [
    "-DRTU_CLMUL_MIN=16",
    "-DRTU_VCLMUL_MIN=2",
    "-DRTU_DISPATCH_CLMUL=1",
    "-DRTU_DISPATCH_VCLMUL=2",
]
SANITIZE = ["-fsanitize=address,undefined", "-fno-sanitize-recover=undefined", "-g"]


def _compiler() -> str:
    for name in ("clang-14", "clang", "gcc", "cc"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no C compiler")


def _build(tmp_path: Path, defines: list[str]) -> Path:
    cc = _compiler()
    exe = tmp_path / "crc_paths"
    base = [cc, "-std=c99", "-O1", "-Wall", "-Wextra", "-Werror", f"-I{ROOT / 'csrc'}"]
    sources = [str(ROOT / "tests/core/csrc/crc_paths.c"), str(ROOT / "csrc/rtu_crc.c")]
    for extra in (SANITIZE, []):
        cmd = [*base, *extra, *defines, *sources, "-o", str(exe)]
        if subprocess.run(cmd, capture_output=True, text=True).returncode == 0:
            return exe
    res = subprocess.run(cmd, capture_output=True, text=True)
    pytest.fail(f"cannot compile tests/core/csrc/crc_paths.c:\n{res.stderr}")


def _cpu_has_pclmul() -> bool:
    try:
        return "pclmulqdq" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("defines", [[], LOWERED], ids=["production", "lowered-thresholds"])
def test_every_crc_path_every_length_and_alignment(tmp_path: Path, defines: list[str]) -> None:
    exe = _build(tmp_path, defines)
    res = subprocess.run(
        [str(exe)],
        capture_output=True,
        text=True,
        env={"ASAN_OPTIONS": "detect_leaks=0", "UBSAN_OPTIONS": "print_stacktrace=1"},
        timeout=600,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    lines = res.stdout.split()
    assert "MISMATCH" not in res.stdout
    assert res.stdout.rstrip().splitlines()[-1].startswith("ok ")
    ran = dict(zip(lines[0:8:2], lines[1:8:2], strict=True))
    assert ran["bytewise"] == ran["slice8"] == "ran"
    if _cpu_has_pclmul():
        assert ran["clmul"] == "ran"
    # 1101 lengths x 8 alignments x 3 seeds, each against the dispatcher and every
    # path that runs here
    paths = sum(1 for v in ran.values() if v == "ran")
    assert int(lines[-1]) == 1101 * 8 * 3 * (paths + 1)
