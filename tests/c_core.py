"""The C core in tests: without it a test skips, but with ``PYRTU_REQUIRE_C=1`` (CI,
``make test-asan``) it fails, so that a build that lost its C core cannot pass by
skipping everything that needs it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pyrtu

ROOT = Path(__file__).resolve().parents[1]


def required() -> bool:
    return os.environ.get("PYRTU_REQUIRE_C") == "1"


def missing(what: str = "the C core is not built here") -> None:
    """Skip the running test for ``what`` (a missing C part), or fail it when the C
    core is required."""
    if required():
        pytest.fail(f"PYRTU_REQUIRE_C=1 but {what}")
    pytest.skip(what)


def need_c() -> None:
    """Skip (or fail, see `missing`) the running test when the C core is not built."""
    if "c" not in pyrtu.available_backends():
        missing()


def needs_c(absent: bool, reason: str = "the C core is not built here") -> pytest.MarkDecorator:
    """``skipif(absent)`` that honours ``PYRTU_REQUIRE_C=1`` (tests/conftest.py reads
    the ``c_core`` mark when the test is set up)."""
    return pytest.mark.c_core(absent=absent, reason=reason)


def build_variant(base: Path, timeout: float = 900, **build_env: str) -> Path:
    """pyrtu with its C core built anew under ``build_env`` (e.g. PYRTU_TLS="0",
    PYRTU_POSIX_IO="0"; strict and required), in ``base``: a directory for PYTHONPATH
    holding the package and its extensions (the caller checks a compiler exists)."""
    lib = base / "lib"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    env.pop("PYTHONPATH", None)
    env.update(PYRTU_REQUIRE_C="1", PYRTU_STRICT_BUILD="1", **build_env)
    cmd = [sys.executable, "setup.py", "-q", "build_ext", "--build-lib", str(lib)]
    cmd += ["--build-temp", str(base / "temp"), "--force"]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    shutil.copytree(
        ROOT / "pyrtu",
        lib / "pyrtu",
        ignore=shutil.ignore_patterns("*.so", "__pycache__"),
        dirs_exist_ok=True,
    )
    return lib
