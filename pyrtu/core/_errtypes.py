"""Exception types that the lowest layers raise (a leaf module: it imports nothing)."""

from __future__ import annotations


class ArgumentTypeError(TypeError, ValueError):
    """An argument of the wrong type: a TypeError, and a ValueError as well so that
    code written when every bad argument raised ValueError still catches it."""


__all__ = ["ArgumentTypeError"]
