"""A package's submodules on first use (a leaf module): ``pyrtu.bridge.outbox`` after
``import pyrtu`` alone, as the documentation writes it, without importing every
submodule (and its dependencies: asyncio, paho-mqtt, protobuf) up front."""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Mapping
from typing import Any


def lazy_attributes(package: str, names: Mapping[str, str] | None = None) -> Callable[[str], Any]:
    """The module ``__getattr__`` of ``package``: each of ``names`` (a name -> the
    module that defines it) and each submodule, imported when first asked for."""
    homes = dict(names or {})

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is not None:
            return getattr(importlib.import_module(home), name)
        if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}"):
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__


__all__ = ["lazy_attributes"]
