"""Install and backend selection, for real: pip in a fresh virtual environment."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the test extra installs tomli there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent


def _run(cmd: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    # no PYRTU_ switches, and no pip settings (indexes, find-links) from the caller
    full_env = {k: v for k, v in os.environ.items() if not k.startswith(("PYRTU_", "PIP_"))}
    full_env.update(env)
    return subprocess.run(cmd, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=300)


def _requirements() -> list[str]:
    """What an install of pyrtu needs: the build system's and the package's requirements."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return [*meta["build-system"]["requires"], *meta["project"]["dependencies"]]


def _closure(names: list[str]) -> list[metadata.Distribution]:
    """The installed distributions of `names` and of what they require, transitively."""
    found: dict[str, metadata.Distribution] = {}
    todo = [Requirement(n) for n in names]
    while todo:
        req = todo.pop()
        key = canonicalize_name(req.name)
        if key in found or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        dist = metadata.distribution(req.name)  # PackageNotFoundError: `make setup` missed it
        assert dist.version in req.specifier, f"{req}: {dist.version} installed"
        found[key] = dist
        todo += [Requirement(r) for r in dist.requires or ()]
    return list(found.values())


def _install_copy(dist: metadata.Distribution, site: Path) -> None:
    """Install `dist` into `site` from its files in this environment (as pip laid them out).

    A wheel install is the wheel's files unpacked into site-packages plus its
    .dist-info; copying them is that install again, with no index and no network.
    Console scripts (outside site-packages) are left out.
    """
    for rel in dist.files or ():
        if ".." in rel.parts or rel.suffix == ".pyc":
            continue
        dest = site / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(str(dist.locate_file(rel)), dest)


@pytest.fixture(scope="module")
def no_compiler_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pyrtu installed with no working C compiler (CC=false), in a venv of its own.

    The venv sees nothing of the system interpreter's packages: what the build
    and the package need (pyproject.toml's build requirements and dependencies,
    and theirs) is installed into it from this test environment (`make setup`
    put them there), and pip runs with ``--no-index``, so a missing requirement
    fails the install instead of being fetched or borrowed.
    """
    base = tmp_path_factory.mktemp("nocc")
    src = base / "src"
    shutil.copytree(
        ROOT, src, ignore=shutil.ignore_patterns(".venv", "build", "*.so", ".git", "__pycache__")
    )
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    assert site.is_relative_to(venv), site
    present = {
        canonicalize_name(d.metadata["Name"]) for d in metadata.distributions(path=[str(site)])
    }
    for dist in _closure(_requirements()):
        if (
            canonicalize_name(dist.metadata["Name"]) not in present
        ):  # the venv's own pip/setuptools stay
            _install_copy(dist, site)
    result = _run(
        [str(py), "-m", "pip", "install", "--no-build-isolation", "--no-index", "-v", "."],
        src,
        CC="false",
        LDSHARED="false",
        PIP_CONFIG_FILE=os.devnull,  # no site or user pip configuration either
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


# A warning on every compile of the core ("the frame size of N bytes is larger than 1
# bytes"), the stand-in for one a newer compiler adds on a user's machine.  (Not
# -Wformat-security: Debian's Python builds extensions with -Werror=format-security.)
WARNING_CFLAGS = "-Wframe-larger-than=1"


def _build_core(tmp: Path, **env: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    """Compile the C core (setup.py build_ext) into `tmp` with CFLAGS adding a warning."""
    lib = tmp / "lib"
    cmd = [sys.executable, "setup.py", "-q", "build_ext"]
    cmd += ["--build-lib", str(lib), "--build-temp", str(tmp / "temp"), "--force"]
    # PYRTU_REQUIRE_C=1: a failed compile fails the command instead of falling back
    out = _run(cmd, ROOT, CFLAGS=WARNING_CFLAGS, PYRTU_REQUIRE_C="1", **env)
    return out, lib


def test_compiler_warnings_fail_only_a_strict_build(tmp_path: Path) -> None:
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(os.environ.get("CC", cc)) is None:
        pytest.skip("no C compiler here")
    plain, lib = _build_core(tmp_path / "plain")
    log = plain.stdout + plain.stderr
    if "-Wframe-larger-than" not in log:
        pytest.skip(f"this compiler does not warn about {WARNING_CFLAGS}: {log[-500:]}")
    assert plain.returncode == 0, log[-3000:]
    assert "-Werror=frame-larger-than" not in log
    assert list((lib / "pyrtu" / "core").glob("_rtu_core*.so")), log[-3000:]

    strict, lib = _build_core(tmp_path / "strict", PYRTU_STRICT_BUILD="1")
    log = strict.stdout + strict.stderr
    assert strict.returncode != 0, log[-3000:]
    assert "-Werror=frame-larger-than" in log, log[-3000:]
    assert not list((lib / "pyrtu" / "core").glob("_rtu_core*.so"))


def test_sdist_and_wheel_carry_the_crc_builtins(tmp_path: Path) -> None:
    """The sdist holds csrc/python/ (MANIFEST.in), and the wheel built from it holds both
    extensions: the cffi core and pyrtu.core._crcfast (setup.py), with its type stub."""
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(os.environ.get("CC", cc)) is None:
        pytest.skip("no C compiler here")
    import tarfile
    import zipfile

    src = tmp_path / "src"
    shutil.copytree(
        ROOT, src, ignore=shutil.ignore_patterns(".venv", "build", "*.so", ".git", "__pycache__")
    )
    sdist = _run([sys.executable, "setup.py", "-q", "sdist", "-d", str(tmp_path / "sdist")], src)
    assert sdist.returncode == 0, sdist.stderr[-3000:]
    (tarball,) = (tmp_path / "sdist").glob("pyrtu-*.tar.gz")
    with tarfile.open(tarball) as tar:
        members = {m.name.split("/", 1)[1] for m in tar.getmembers() if "/" in m.name}
    assert {"csrc/python/rtu_crc_py.c", "csrc/rtu_crc.c", "pyrtu/core/_crcfast.pyi"} <= members
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-build-isolation", "--no-deps"]
    cmd += ["--no-index", "-w", str(tmp_path / "dist"), str(tarball)]
    # PYRTU_REQUIRE_C=1: a failed compile of either extension fails the build
    wheel = _run(cmd, tmp_path, PYRTU_REQUIRE_C="1", PIP_CONFIG_FILE=os.devnull)
    assert wheel.returncode == 0, wheel.stdout[-3000:] + wheel.stderr[-3000:]
    (whl,) = (tmp_path / "dist").glob("pyrtu-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    assert [n for n in names if n.startswith("pyrtu/core/_crcfast.") and n.endswith(".so")], names
    assert [n for n in names if n.startswith("pyrtu/core/_rtu_core.") and n.endswith(".so")], names
    assert "pyrtu/core/_crcfast.pyi" in names
