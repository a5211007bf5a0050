"""Shared fixtures: every core test runs against both backends.

No silent skip in CI: with ``CI=true`` in the environment (set by CI's runner and by
.ci/run) a test that skips fails instead, unless its skip is on `ALLOWED_SKIPS` below,
each entry with its reason; so a missing package (strace, mosquitto, libmodbus, a
Python library) fails CI instead of quietly leaving its tests out.  The C core:
``PYRTU_REQUIRE_C=1`` makes a test that needs it fail where it would skip
(tests/c_core.py).
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Generator, Iterator
from types import ModuleType

import pytest
from c_core import missing

import pyrtu

BACKENDS = ("c", "python")

#: The skips CI allows: (test file, words of the skip's reason) -> why it may skip
#: there.  Keep this short; anything CI can install belongs in the Makefile
#: (APT_PACKAGES) or in pyproject.toml's test extras instead.
ALLOWED_SKIPS: dict[tuple[str, str], str] = {
    ("tests/drivers/test_ptimer.py", "timerfd is Linux's"): "a Linux-only timer (CI runs on Linux)",
    (
        "tests/drivers/test_slave_driver.py",
        "no prctl timer slack",
    ): "prctl is Linux's (CI runs on Linux)",
}


def ci() -> bool:
    """Whether skips fail (``CI`` set to true, as CI runners and .ci/run do)."""
    return os.environ.get("CI", "").lower() in ("true", "1", "yes")


def allowed(nodeid: str, reason: str) -> bool:
    path = nodeid.split("::", 1)[0]
    return any(path == file and words in reason for file, words in ALLOWED_SKIPS)


def _reason(longrepr: object) -> str:
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2])
    return str(longrepr)


def _no_skip(report: pytest.TestReport | pytest.CollectReport) -> None:
    if not report.skipped or not ci() or hasattr(report, "wasxfail"):
        return
    reason = _reason(report.longrepr)
    if allowed(report.nodeid, reason):
        return
    report.outcome = "failed"
    report.longrepr = (
        f"skipped in CI (CI=true), which allows no skip but those listed in tests/conftest.py "
        f"ALLOWED_SKIPS: {reason}\n(install what the test needs: the Makefile's APT_PACKAGES, "
        "pyproject.toml's test extras; or list it there with a reason)"
    )


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, None]:
    outcome = yield
    _no_skip(outcome.get_result())  # type: ignore[attr-defined]


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector: pytest.Collector) -> Generator[None, object, None]:
    outcome = yield
    _no_skip(outcome.get_result())  # type: ignore[attr-defined]


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "c_core(absent, reason): skip when absent, fail instead with PYRTU_REQUIRE_C=1 "
        "(tests/c_core.py needs_c)",
    )


def pytest_runtest_setup(item: pytest.Item) -> None:
    mark = item.get_closest_marker("c_core")
    if mark is not None and mark.kwargs.get("absent"):
        missing(str(mark.kwargs.get("reason", "the C core is not built here")))


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> ModuleType:
    """The C core and the pure-Python twin in turn."""
    name = request.param
    if name not in pyrtu.available_backends():
        missing()
    return pyrtu.backend(name)


@pytest.fixture
def both() -> tuple[ModuleType, ModuleType]:
    """(C, Python), for tests that compare the two."""
    if "c" not in pyrtu.available_backends():
        missing()
    return pyrtu.backend("c"), pyrtu.backend("python")


@pytest.fixture
def loop() -> Iterator[asyncio.AbstractEventLoop]:
    """An event loop running on a thread of its own (servers under test on it, the
    test's clients in the test's thread: `asyncio.run_coroutine_threadsafe`)."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    yield loop
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()
