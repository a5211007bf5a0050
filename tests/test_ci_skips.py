"""tests/conftest.py's rule for CI: with CI=true a skip fails, but those listed in
ALLOWED_SKIPS; without it a skip is a skip.  Run on a small copy of the hook."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

HERE = Path(__file__).parent

TESTS = {
    "test_some.py": """
import pytest

def test_runs():
    pass

def test_skips_at_run_time():
    pytest.skip("strace is not installed")

@pytest.mark.skipif(True, reason="a missing library")
def test_skips_by_mark():
    pass
""",
    "test_gone.py": """
import pytest
pytest.importorskip("no_such_module_anywhere")

def test_never():
    pass
""",
    # an allowed skip: this file and these words are in ALLOWED_SKIPS
    "drivers/test_ptimer.py": """
import pytest

def test_linux_only():
    pytest.skip("timerfd is Linux's")
""",
}


def run(
    pytester: pytest.Pytester,
    monkeypatch: pytest.MonkeyPatch,
    ci: str | None,
    files: tuple[str, ...] = ("test_some.py", "drivers/test_ptimer.py"),
) -> pytest.RunResult:
    tests = pytester.path / "tests"
    tests.mkdir()
    for name in ("conftest.py", "c_core.py"):
        shutil.copy(HERE / name, tests / name)
    for name in files:
        (tests / name).parent.mkdir(exist_ok=True)
        (tests / name).write_text(TESTS[name])
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    return pytester.runpytest_subprocess("tests", "-rs", "-p", "no:cacheprovider")


def test_in_ci_a_skip_fails_unless_allowed(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    result = run(pytester, monkeypatch, "true")
    # the run-time skip fails, the mark's (at set-up) is an error; the allowed one
    # stays a skip
    result.assert_outcomes(passed=1, failed=1, errors=1, skipped=1)
    assert result.ret != 0
    out = result.stdout.str()
    assert "skipped in CI (CI=true)" in out and "strace is not installed" in out
    assert "a missing library" in out
    assert "SKIPPED" in out and "timerfd is Linux's" in out  # -rs lists the allowed skip


def test_in_ci_a_module_that_skips_is_a_collection_error(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    result = run(pytester, monkeypatch, "true", ("test_gone.py",))
    result.assert_outcomes(errors=1)
    assert "skipped in CI (CI=true)" in result.stdout.str()
    assert result.ret != 0


def test_outside_ci_a_skip_is_a_skip(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    result = run(pytester, monkeypatch, None, tuple(TESTS))
    result.assert_outcomes(passed=1, skipped=4)
