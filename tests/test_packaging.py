"""Install and backend selection, for real: pip in a fresh virtual environment."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _run(cmd: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    full_env.update(env)
    return subprocess.run(cmd, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def no_compiler_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pyrtu installed with no working C compiler (CC=false)."""
    base = tmp_path_factory.mktemp("nocc")
    src = base / "src"
    shutil.copytree(
        ROOT, src, ignore=shutil.ignore_patterns(".venv", "build", "*.so", ".git", "__pycache__")
    )
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    py = venv / "bin" / "python"
    result = _run(
        [str(py), "-m", "pip", "install", "--no-build-isolation", "--no-deps", "-v", "."],
        src,
        CC="false",
        LDSHARED="false",
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "Installing the pure-Python backend only" in result.stdout + result.stderr
    return py


def test_install_without_compiler_gives_the_twin(no_compiler_venv: Path, tmp_path: Path) -> None:
    out = _run(
        [
            str(no_compiler_venv),
            "-c",
            "import pyrtu; print(pyrtu.BACKEND, pyrtu.crc16(b'123456789'))",
        ],
        tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["python", str(0x4B37)]


def test_require_c_refuses_the_twin(no_compiler_venv: Path, tmp_path: Path) -> None:
    out = _run([str(no_compiler_venv), "-c", "import pyrtu"], tmp_path, PYRTU_REQUIRE_C="1")
    assert out.returncode != 0
    assert "PYRTU_REQUIRE_C=1 but the pyrtu C core is not built" in out.stderr


def test_pure_switch_and_backend_attribute(tmp_path: Path) -> None:
    code = "import pyrtu; print(pyrtu.BACKEND, pyrtu.available_backends())"
    pure = _run([sys.executable, "-c", code], tmp_path, PYRTU_PURE="1", PYTHONPATH=str(ROOT))
    assert pure.returncode == 0, pure.stderr
    assert pure.stdout.startswith("python ")
    default = _run([sys.executable, "-c", code], tmp_path, PYTHONPATH=str(ROOT))
    assert default.returncode == 0, default.stderr
    if "'c'" in default.stdout:
        assert default.stdout.startswith("c ")
