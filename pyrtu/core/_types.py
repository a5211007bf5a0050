"""Type aliases shared across the package, and what both backends share: the argument
check of their CRC functions, the names each exports (`BACKEND_NAMES`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Buffer as BytesLike
else:  # any object with the buffer protocol; checked at run time by memoryview()
    BytesLike = object


#: the names both backends (pyrtu/core/_cext.py and its twin pyrtu/core/_pure/) export
BACKEND_NAMES = (
    "BACKEND",
    "Framer",
    "MbapFramer",
    "add_crc",
    "char_timing",
    "check_crc",
    "crc16",
    "crc16_path",
    "crc16_paths",
    "encode_mbap",
    "lrc",
    "parse_stream",
    "parse_tcp_stream",
    "request_predictor",
)


def crc_seed(crc: int) -> int:
    """``crc`` as a CRC-16 start value (0..0xFFFF): TypeError or ValueError otherwise."""
    if isinstance(crc, bool) or not isinstance(crc, int):
        raise TypeError(f"crc must be an integer 0..0xFFFF, not {type(crc).__name__}")
    if not 0 <= crc <= 0xFFFF:
        raise ValueError(f"crc must be an integer 0..0xFFFF, not {crc!r}")
    return crc


__all__ = ["BACKEND_NAMES", "BytesLike", "crc_seed"]
