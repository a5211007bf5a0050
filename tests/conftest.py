"""Shared fixtures: every core test runs against both backends."""

from __future__ import annotations

import os
from types import ModuleType

import pytest

import pyrtu

BACKENDS = ("c", "python")


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> ModuleType:
    """The C core and the pure-Python twin in turn."""
    name = request.param
    if name not in pyrtu.available_backends():
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            pytest.fail("PYRTU_REQUIRE_C=1 but the C core is not built")
        pytest.skip("the C core is not built here")
    return pyrtu.backend(name)


@pytest.fixture
def both() -> tuple[ModuleType, ModuleType]:
    """(C, Python), for tests that compare the two."""
    if "c" not in pyrtu.available_backends():
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            pytest.fail("PYRTU_REQUIRE_C=1 but the C core is not built")
        pytest.skip("the C core is not built here")
    return pyrtu.backend("c"), pyrtu.backend("python")
