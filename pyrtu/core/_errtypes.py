"""Exception types that the lowest layers raise (a leaf module: it imports nothing)."""

from __future__ import annotations


class ArgumentTypeError(TypeError, ValueError):
    """An argument of the wrong type: a TypeError, and a ValueError as well so that
    code written when every bad argument raised ValueError still catches it."""


class PureBackendWarning(RuntimeWarning):
    """``import pyrtu`` found no C core (an install without a C compiler): the pure-Python
    twin runs, with the same results, slower.  ``PYRTU_PURE=1`` chooses the twin on
    purpose and is not warned about; ``PYRTU_REQUIRE_C=1`` makes the import fail."""


__all__ = ["ArgumentTypeError", "PureBackendWarning"]
