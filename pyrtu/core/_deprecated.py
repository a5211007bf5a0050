"""Deprecated names and paths (a leaf module): a module's ``__getattr__`` that finds an
old name at its new home and warns, naming the new one.

    __getattr__ = renamed(__name__, {"Xfer": ("pyrtu.protocol.client_actions", "Xfer")})

Each use of an old name emits `DeprecationWarning` (``stacklevel`` at the user's line)
saying ``old is deprecated: use new``; the value is the new name's object itself.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping
from typing import Any


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """The one deprecation message: ``old`` is deprecated, use ``new``."""
    warnings.warn(f"{old} is deprecated: use {new}", DeprecationWarning, stacklevel=stacklevel)


def renamed(module: str, aliases: Mapping[str, tuple[str, str]]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``module``: ``aliases`` maps each old name to its
    new home and name (``(module path, name)``)."""

    def __getattr__(name: str) -> Any:
        home = aliases.get(name)
        if home is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        new_module, new_name = home
        warn_renamed(f"{module}.{name}", f"{new_module}.{new_name}")
        return getattr(importlib.import_module(new_module), new_name)

    return __getattr__


def moved(module: str, new_module: str, names: list[str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for a deprecated module path whose ``names`` live on,
    under the same names, in ``new_module``."""
    return renamed(module, {name: (new_module, name) for name in names})


__all__ = ["moved", "renamed", "warn_renamed"]
