"""Module-attribute patches that can be undone (shared by the CRC adapters)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from types import ModuleType
from typing import Any


class Patches:
    """A set of ``(module, attribute) -> replacement`` applied together, undone together."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._saved: list[tuple[ModuleType, str, Any]] = []

    @property
    def active(self) -> bool:
        return bool(self._saved)

    def apply(self, replacements: list[tuple[ModuleType, str, Any]]) -> None:
        """Replace each attribute (after undoing an earlier apply)."""
        self.undo()
        for module, attr, new in replacements:
            self._saved.append((module, attr, getattr(module, attr)))
            setattr(module, attr, new)

    def undo(self) -> None:
        while self._saved:
            module, attr, old = self._saved.pop()
            setattr(module, attr, old)


@contextmanager
def patched_block(install: Callable[[], None], uninstall: Callable[[], None]) -> Iterator[None]:
    """``install()`` for a ``with`` block, ``uninstall()`` after it."""
    install()
    try:
        yield
    finally:
        uninstall()


def crc_adapter_api(
    patches: Patches, install: Callable[[], None]
) -> tuple[Callable[[], None], Callable[[], bool], Callable[[], AbstractContextManager[None]]]:
    """``uninstall``, ``installed`` and ``patched`` of a CRC adapter whose ``install``
    applies ``patches`` (the three are the same for every such adapter)."""

    def uninstall() -> None:
        patches.undo()

    def installed() -> bool:
        return patches.active

    def patched() -> AbstractContextManager[None]:
        return patched_block(install, uninstall)

    uninstall.__doc__ = f"{patches.name}'s own CRC again."
    patched.__doc__ = "`install` for a ``with`` block."
    return uninstall, installed, patched
