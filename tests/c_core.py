"""The C core in tests: without it a test skips, but with ``PYRTU_REQUIRE_C=1`` (CI,
``make test-asan``) it fails, so that a build that lost its C core cannot pass by
skipping everything that needs it."""

from __future__ import annotations

import os

import pytest

import pyrtu


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
