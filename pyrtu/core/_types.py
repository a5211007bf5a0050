"""Type aliases shared across the package, and the argument check both backends' CRC
functions share."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Buffer as BytesLike
else:  # any object with the buffer protocol; checked at run time by memoryview()
    BytesLike = object


def crc_seed(crc: int) -> int:
    """``crc`` as a CRC-16 start value (0..0xFFFF): TypeError or ValueError otherwise."""
    if isinstance(crc, bool) or not isinstance(crc, int):
        raise TypeError(f"crc must be an integer 0..0xFFFF, not {type(crc).__name__}")
    if not 0 <= crc <= 0xFFFF:
        raise ValueError(f"crc must be an integer 0..0xFFFF, not {crc!r}")
    return crc


__all__ = ["BytesLike", "crc_seed"]
