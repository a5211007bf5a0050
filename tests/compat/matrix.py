"""The pymodbus compat tests against every tested pymodbus release (`make compat-matrix`).

    python tests/compat/matrix.py                    # every release, one after another
    python tests/compat/matrix.py --jobs 2           # two releases at a time
    python tests/compat/matrix.py 3.13.1 3.16.1      # some of them
    python tests/compat/matrix.py --list             # the releases, one a line

The releases are pyrtu.compat.PYMODBUS_RELEASES (pyrtu/compat/_guard.py, the one list;
docs/COMPAT.md shows it, tests/compat/test_compat_matrix.py checks they agree).  For
each, a virtual environment build/compat-matrix/pymodbus-<release>/ (made once with
this interpreter's base Python, kept between runs: a marker file records what was
installed) holds that pymodbus, pytest and pyrtu's own dependencies; pyrtu itself comes
from this tree through PYTHONPATH, with the C core already built here (`make setup`),
so every release runs the same core.  There it runs the pymodbus compat test files
(`TEST_FILES`) and prints the pass counts per release; the exit status is 1 when any
release fails (or when PYRTU_REQUIRE_C=1 and the C core is not built).  Each run's
output is in build/compat-matrix/pymodbus-<release>.log.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from pyrtu.compat._guard import PYMODBUS_RELEASES  # noqa: E402

#: the releases this script runs: pyrtu.compat's list, not a copy
RELEASES = PYMODBUS_RELEASES
#: the test files run against each release (the pymodbus ones of tests/compat/)
TEST_FILES = ("tests/compat/test_compat_pymodbus.py", "tests/compat/test_compat_pymodbus_bus.py")
#: what each environment gets besides pymodbus: the test runner and pyrtu's own
#: run-time dependencies (pyproject.toml's ``dependencies``)
REQUIREMENTS = ("pytest>=7", "cffi>=1.15", "pyserial>=3.5")
MATRIX_DIR = ROOT / "build" / "compat-matrix"


@dataclass
class Outcome:
    release: str
    counts: dict[str, int]
    seconds: float
    returncode: int
    log: Path

    @property
    def ok(self) -> bool:
        return self.returncode == 0 and self.counts.get("passed", 0) > 0


def environment(release: str) -> Path:
    """The virtual environment of ``release``, made and filled when it is missing or
    was filled with other requirements."""
    home = MATRIX_DIR / f"pymodbus-{release}"
    python = home / "bin" / "python"
    wanted = "\n".join((f"pymodbus=={release}", *REQUIREMENTS)) + "\n"
    marker = home / ".installed"
    if python.exists() and marker.exists() and marker.read_text() == wanted:
        return python
    base = getattr(sys, "_base_executable", sys.executable)
    if not python.exists():
        # the base interpreter of this one: the C core built here loads in it
        subprocess.run([base, "-m", "venv", str(home)], check=True)
    pip_log = MATRIX_DIR / f"pymodbus-{release}.pip.log"
    with pip_log.open("w") as out:
        done = subprocess.run(
            [str(python), "-m", "pip", "install", "--disable-pip-version-check", *wanted.split()],
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    if done.returncode != 0:
        sys.stderr.write(pip_log.read_text())
        raise SystemExit(f"compat-matrix: pip could not install pymodbus {release} ({pip_log})")
    marker.write_text(wanted)
    return python


def run(release: str) -> Outcome:
    """``release``'s environment (made when missing), then the test files in it."""
    python = environment(release)
    log = MATRIX_DIR / f"pymodbus-{release}.log"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("VIRTUAL_ENV", None)
    start = time.monotonic()
    with log.open("w") as out:
        done = subprocess.run(
            [str(python), "-m", "pytest", "-q", "-rfEs", "-p", "no:cacheprovider", *TEST_FILES],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    text = log.read_text()
    summary = text.strip().splitlines()[-1] if text.strip() else ""
    counts = {
        word: int(n)
        for n, word in re.findall(r"(\d+) (passed|failed|errors?|skipped|xfailed|xpassed)", summary)
    }
    return Outcome(release, counts, time.monotonic() - start, done.returncode, log)


def core_check() -> str | None:
    """Why the C core cannot run here (None: it can), for PYRTU_REQUIRE_C=1."""
    if os.environ.get("PYRTU_REQUIRE_C") != "1":
        return None
    import pyrtu

    return None if pyrtu.BACKEND == "c" else "the C core is not built (make setup)"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("releases", nargs="*", help="pymodbus releases (default: all tested)")
    parser.add_argument("--jobs", type=int, default=1, help="releases run at a time")
    parser.add_argument("--list", action="store_true", help="print the releases and exit")
    args = parser.parse_args(argv)
    if args.list:
        print("\n".join(RELEASES))
        return 0
    unknown = [r for r in args.releases if r not in RELEASES]
    if unknown:
        parser.error(f"not a tested pymodbus release: {', '.join(unknown)} (see --list)")
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    if (why := core_check()) is not None:
        print(f"compat-matrix: {why}", file=sys.stderr)
        return 1
    releases = args.releases or list(RELEASES)
    MATRIX_DIR.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    with ThreadPoolExecutor(args.jobs) as pool:
        outcomes = list(pool.map(run, releases))
    failed = 0
    for o in outcomes:
        counts = ", ".join(f"{n} {word}" for word, n in o.counts.items()) or "no summary"
        print(f"pymodbus {o.release:8} {'ok  ' if o.ok else 'FAIL'} {counts} ({o.seconds:.0f} s)")
        if not o.ok:
            failed += 1
            print("".join(o.log.read_text().splitlines(keepends=True)[-30:]), file=sys.stderr)
    print(
        f"compat-matrix: {len(outcomes) - failed} of {len(outcomes)} releases green "
        f"in {time.monotonic() - start:.0f} s (logs: {MATRIX_DIR.relative_to(ROOT)}/)"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
