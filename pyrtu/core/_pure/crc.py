"""CRC-16/MODBUS and LRC in pure Python (the twin of csrc/rtu_crc.c, rtu_lrc.c).

The tables are the auchCRCHi / auchCRCLo of the manuals' Appendix B (Modbus over
Serial Line V1.02, 6.2.2), generated from the reflected polynomial 0xA001.
"""

from __future__ import annotations

from pyrtu.core._types import BytesLike as Buffer
from pyrtu.core._types import crc_seed


def _make_tables() -> tuple[bytes, bytes]:
    hi = bytearray(256)
    lo = bytearray(256)
    for i in range(256):
        crc = i
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        # The Appendix B loop keeps the register byte-swapped.
        hi[i] = crc & 0xFF
        lo[i] = crc >> 8
    return bytes(hi), bytes(lo)


AUCH_CRC_HI, AUCH_CRC_LO = _make_tables()
_TABLE16 = tuple(AUCH_CRC_HI[i] | AUCH_CRC_LO[i] << 8 for i in range(256))


def _as_bytes(data: Buffer, name: str = "data") -> memoryview:
    try:
        view = memoryview(data)
    except TypeError:
        raise TypeError(f"{name} must be a bytes-like object, not {type(data).__name__}") from None
    if not view.c_contiguous:  # strided: its bytes in logical order, as C copies them
        return memoryview(view.tobytes())
    return view.cast("B") if view.format != "B" or view.ndim != 1 else view


def crc16(data: Buffer, crc: int = 0xFFFF) -> int:
    """CRC-16/MODBUS of ``data``, continuing from ``crc`` (0xFFFF to start)."""
    view = _as_bytes(data)
    crc = crc_seed(crc)
    table = _TABLE16
    for byte in view.tobytes():
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def add_crc(data: Buffer) -> bytes:
    """``data`` with its CRC appended, low byte first (CFW100 4.2.4)."""
    raw = _as_bytes(data).tobytes()
    crc = crc16(raw)
    return raw + bytes((crc & 0xFF, crc >> 8))


def check_crc(adu: Buffer) -> bool:
    """True when the last two bytes of ``adu`` are the CRC of the rest."""
    raw = _as_bytes(adu, "adu").tobytes()
    if len(raw) < 3:
        return False
    crc = crc16(raw[:-2])
    return raw[-2] == crc & 0xFF and raw[-1] == crc >> 8


def lrc(data: Buffer) -> int:
    """LRC of ASCII mode: two's complement of the 8-bit byte sum (seed 004, 6.7.2.3)."""
    return -sum(_as_bytes(data).tobytes()) & 0xFF


PATHS = ("bytewise",)


def crc16_paths() -> tuple[str, ...]:
    return PATHS


def crc16_path(path: str, data: Buffer, crc: int = 0xFFFF) -> int:
    if path not in PATHS:
        raise ValueError(f"crc16_path: the python backend has no {path!r} path (has {PATHS})")
    return crc16(data, crc)
