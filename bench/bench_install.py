"""Install time and wheel size (issue 32, item 1).

    python bench/bench_install.py [--runs 3] [--json FILE]

Builds an sdist and a wheel of this checkout with ``python -m build`` (build isolation:
its requirements from the index, as a user's build gets them), repairs the wheel with
auditwheel (the manylinux tag its symbols allow, symbols stripped), then installs into
fresh virtual environments, offline: the dependencies (cffi, pyserial and theirs) are
copied in from this environment (tests/venvs.py), and pip runs with ``--no-index``, so
the time is pyrtu's own install, not a download:

- the repaired wheel, with no compiler on PATH (the user's case this item is about);
- the sdist, compiling the C core (what every install cost before the wheel).

Prints a table; ``--json FILE`` writes the figures for bench/report.py, which puts
them in the section "Install: wheel size and install time" of bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path[:0] = [str(ROOT / "tests"), str(BENCH)]

from venvs import venv_with  # noqa: E402

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

HEADING = "## Install: wheel size and install time (issue 32.1)"
IGNORE = shutil.ignore_patterns(".venv", "build", "dist", "*.so", ".git", "__pycache__")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYRTU_", "PIP_"))}
    env.pop("PYTHONPATH", None)
    env["PIP_CONFIG_FILE"] = os.devnull
    env.update(extra)
    return env


def _check(cmd: list[str], cwd: Path, **extra: str) -> float:
    """Run `cmd`; its wall time (s).  A failure ends the benchmark with its output."""
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=cwd, env=_env(**extra), capture_output=True, text=True)
    elapsed = time.perf_counter() - t0
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{out.stdout[-3000:]}{out.stderr[-3000:]}")
    return elapsed


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _requirements(build: bool) -> list[str]:
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    deps = list(meta["project"]["dependencies"])
    return [*meta["build-system"]["requires"], *deps] if build else deps


@dataclass(frozen=True)
class Result:
    date: str
    machine: str
    python: str
    load: str  # the 1-minute load average before and after (a shared machine is noisy)
    build_s: float
    sdist: Path
    raw: Path  # the wheel as setuptools built it
    wheel: Path  # repaired and stripped by auditwheel
    installed: int  # bytes pyrtu takes in site-packages
    wheel_s: list[float]
    sdist_s: list[float]


def _site(py: Path) -> Path:
    return next((py.parent.parent / "lib").glob("python*/site-packages"))


def _pyrtu_size(py: Path) -> int:
    """What pyrtu takes in the venv's site-packages (the package and its dist-info)."""
    return sum(_size(p) for p in _site(py).glob("pyrtu*"))


def measure(runs: int, keep: Path) -> Result:
    """Build, repair and install `runs` times; the distributions are copied to `keep`."""
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        src = tmp / "src"
        shutil.copytree(ROOT, src, ignore=IGNORE)
        out, fixed = tmp / "out", tmp / "fixed"
        build = [sys.executable, "-m", "build", "--outdir", str(out), str(src)]
        build_s = _check(build, tmp, PYRTU_REQUIRE_C="1")
        (sdist,) = out.glob("*.tar.gz")
        (raw,) = out.glob("*.whl")
        path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
        fix = [sys.executable, "-m", "auditwheel", "repair", "--strip", "-w", str(fixed)]
        _check([*fix, str(raw)], tmp, PATH=path)
        (wheel,) = fixed.glob("*.whl")
        wheel_s: list[float] = []
        sdist_s: list[float] = []
        installed = 0
        for i in range(runs):
            py = venv_with(tmp / f"w{i}", _requirements(build=False))
            cmd = [str(py), "-m", "pip", "install", "--no-index", "--only-binary", ":all:"]
            wheel_s.append(_check([*cmd, str(wheel)], tmp, PATH=str(py.parent)))
            probe = "import pyrtu, sys; sys.exit(pyrtu.BACKEND != 'c')"
            _check([str(py), "-c", probe], tmp, PYRTU_REQUIRE_C="1")
            installed = _pyrtu_size(py)
            py = venv_with(tmp / f"s{i}", _requirements(build=True))
            cmd = [str(py), "-m", "pip", "install", "--no-index", "--no-build-isolation"]
            sdist_s.append(_check([*cmd, str(sdist)], tmp, PYRTU_REQUIRE_C="1"))
        keep.mkdir(parents=True, exist_ok=True)
        (keep / "repaired").mkdir(exist_ok=True)
        kept = [
            Path(shutil.copy2(sdist, keep)),
            Path(shutil.copy2(raw, keep)),
            Path(shutil.copy2(wheel, keep / "repaired")),
        ]
        return Result(
            date=datetime.date.today().isoformat(),
            machine=f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
            python=platform.python_version(),
            load=f"{load_before:.1f} before, {os.getloadavg()[0]:.1f} after",
            build_s=build_s,
            sdist=kept[0],
            raw=kept[1],
            wheel=kept[2],
            installed=installed,
            wheel_s=wheel_s,
            sdist_s=sdist_s,
        )


def _kib(path_or_size: Path | int) -> str:
    n = path_or_size if isinstance(path_or_size, int) else path_or_size.stat().st_size
    return f"{n / 1024:.0f} KiB"


def _median(xs: list[float]) -> str:
    return f"{statistics.median(xs):.2f} s (runs: {', '.join(f'{x:.2f}' for x in xs)})"


def section(res: Result, command: str) -> str:
    return "\n".join(
        [
            HEADING,
            "",
            f"`{command}`, {res.date}, {res.machine}, CPython {res.python}; "
            f"load average {res.load} (on {os.cpu_count()} CPUs).",
            "Installs are offline (the dependencies copied into each fresh venv, pip "
            "`--no-index`): the time is pyrtu's own, pip's byte-compiling of the package "
            "included.",
            "",
            "| what | figure |",
            "|---|---|",
            f"| sdist `{res.sdist.name}` | {_kib(res.sdist)} |",
            f"| wheel as built, `{res.raw.name}` | {_kib(res.raw)} |",
            f"| wheel repaired (auditwheel --strip), `{res.wheel.name}` | {_kib(res.wheel)} |",
            f"| pyrtu in site-packages, from the wheel | {_kib(res.installed)} |",
            f"| `python -m build` (sdist, then the wheel from it) | {res.build_s:.1f} s |",
            f"| `pip install` of the wheel, no compiler on PATH | {_median(res.wheel_s)} |",
            f"| `pip install` of the sdist (compiles the C core) | {_median(res.sdist_s)} |",
            "",
        ]
    )


def as_json(res: Result) -> dict[str, object]:
    """The figures as bench/report.py keeps them (sizes in bytes, times in seconds)."""
    return {
        "sdist": {"name": res.sdist.name, "bytes": res.sdist.stat().st_size},
        "wheel_built": {"name": res.raw.name, "bytes": res.raw.stat().st_size},
        "wheel_repaired": {"name": res.wheel.name, "bytes": res.wheel.stat().st_size},
        "installed_bytes": res.installed,
        "build_s": res.build_s,
        "wheel_install_s": res.wheel_s,
        "sdist_install_s": res.sdist_s,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="installs of each kind (default 3)")
    ap.add_argument(
        "--json", type=Path, metavar="FILE", help="also write the figures as JSON (bench/report.py)"
    )
    ap.add_argument(
        "--dist",
        type=Path,
        default=ROOT / "build" / "bench-install",
        help="where the built sdist and wheels are kept (default build/bench-install)",
    )
    ns = ap.parse_args()
    if ns.runs < 1:
        ap.error("--runs must be at least 1")
    res = measure(ns.runs, ns.dist)
    text = section(res, " ".join(["python bench/bench_install.py", *sys.argv[1:]]))
    print(text)
    if ns.json is not None:
        ns.json.write_text(json.dumps(as_json(res), indent=2) + "\n")


if __name__ == "__main__":
    main()
