"""Type aliases shared across the package."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Buffer as BytesLike
else:  # any object with the buffer protocol; checked at run time by memoryview()
    BytesLike = object

__all__ = ["BytesLike"]
