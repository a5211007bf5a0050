"""Both backends export the same names (`pyrtu.core._types.BACKEND_NAMES`), built by
the same factories: the Framer and MbapFramer classes say which backend they are."""

from __future__ import annotations

import pytest

from pyrtu.core._backend import available_backends, backend
from pyrtu.core._types import BACKEND_NAMES


@pytest.mark.parametrize("name", available_backends())
def test_a_backend_defines_and_exports_every_shared_name(name: str) -> None:
    module = backend(name)
    assert [n for n in BACKEND_NAMES if not hasattr(module, n)] == []
    assert set(BACKEND_NAMES) <= set(module.__all__)
    assert module.BACKEND == name


@pytest.mark.parametrize("name", available_backends())
def test_the_framer_classes_belong_to_their_backend(name: str) -> None:
    module = backend(name)
    for cls in (module.Framer, module.MbapFramer):
        assert cls.BACKEND == name
        assert cls.__module__ == module.__name__
        assert cls.__qualname__ == cls.__name__
    framer = module.Framer("master", baudrate=19200)
    assert framer.BACKEND == name
    assert framer.send(b"\x01\x03\x00\x00\x00\x01\x84\x0a") == b"\x01\x03\x00\x00\x00\x01\x84\x0a"
