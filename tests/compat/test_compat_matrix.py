"""The pymodbus releases pyrtu.compat is tested with are one list, and everything that
names them agrees: the version guard (pyrtu/compat/_guard.py), the matrix script
(tests/compat/matrix.py), docs/COMPAT.md, the test extra of pyproject.toml (the main
environment's pymodbus), the Makefile target and the CI step that run the matrix."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import matrix
import pytest

from pyrtu.compat import PYMODBUS_RELEASES, TESTED, UnsupportedVersionError
from pyrtu.compat._guard import _minors, check_version

ROOT = Path(__file__).resolve().parents[2]


def minor(release: str) -> tuple[int, int]:
    major, minor_, *_ = (int(part) for part in release.split("."))
    return major, minor_


def test_releases_cover_3_9_to_3_16_and_home_assistants_pin() -> None:
    """One release per minor, 3.9 to 3.16, in order; 3.13.1 (Home Assistant) among them."""
    minors = [minor(r) for r in PYMODBUS_RELEASES]
    assert minors == [(3, m) for m in range(9, 17)]
    assert "3.13.1" in PYMODBUS_RELEASES


def test_guard_accepts_exactly_the_tested_minors() -> None:
    assert TESTED["pymodbus"] == ((3, 9, 0), (3, 17))
    for release in PYMODBUS_RELEASES:
        check_version("pymodbus", release)
    check_version("pymodbus", "3.9.0")  # the boundaries, both sides
    check_version("pymodbus", "3.16.99")
    for outside in ("3.8.6", "3.17.0", "4.0.0"):
        with pytest.raises(UnsupportedVersionError, match=rf"pymodbus {outside} is installed"):
            check_version("pymodbus", outside)


def test_a_skipped_minor_is_refused() -> None:
    assert _minors(("3.9.2", "3.10.0")) == ((3, 9, 0), (3, 11))
    with pytest.raises(ValueError, match="skip a minor"):
        _minors(("3.9.2", "3.11.4"))


def test_matrix_script_runs_the_guard_list() -> None:
    assert matrix.RELEASES is PYMODBUS_RELEASES
    listed = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "compat" / "matrix.py"), "--list"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert listed == list(PYMODBUS_RELEASES)
    for path in matrix.TEST_FILES:
        assert (ROOT / path).is_file(), path


def test_compat_md_lists_the_releases() -> None:
    text = (ROOT / "docs" / "COMPAT.md").read_text(encoding="utf-8")
    row = re.search(r"^\| pymodbus \| (\d.*) \|$", text, re.MULTILINE)
    assert row is not None, "docs/COMPAT.md: no pymodbus row in the versions table"
    assert re.findall(r"\d+\.\d+\.\d+", row.group(1).split("(", 1)[1]) == list(PYMODBUS_RELEASES)
    low, high = TESTED["pymodbus"]
    assert row.group(1).startswith(f"{low[0]}.{low[1]}.x to {high[0]}.{high[1] - 1}.x")


def test_main_environment_pins_the_last_release() -> None:
    """The test extra installs the newest tested minor (the matrix runs the others)."""
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    pin = re.search(r'"pymodbus>=(\d+)\.(\d+),<(\d+)\.(\d+)"', text)
    assert pin is not None
    last = minor(PYMODBUS_RELEASES[-1])
    assert (int(pin[1]), int(pin[2])) == last and (int(pin[3]), int(pin[4])) == (3, last[1] + 1)


def test_make_and_ci_run_the_matrix() -> None:
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    target = re.search(r"^compat-matrix:.*\n((?:\t.*\n)+)", makefile, re.MULTILINE)
    assert target is not None and "tests/compat/matrix.py" in target.group(1)
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r"^make compat-matrix\b", ci, re.MULTILINE)
