"""The CRC-16/MODBUS in the call shapes other Python Modbus code already uses.

* `crc16_bytes` -- the two CRC bytes, low byte first, as they go on the wire:
  minimalmodbus's ``_calculate_crc`` and umodbus's ``redundancy_check.get_crc``.
* `crc16_swapped` -- the CRC as an integer with its bytes swapped, so that
  ``.to_bytes(2, "big")`` is the wire order: pymodbus's ``FramerRTU.compute_CRC`` and
  modbus_tk's ``utils.calculate_crc``.
* `Crc16` -- crcmod's ``Crc`` object (``crcmod.predefined.Crc("modbus")``): ``update``,
  ``crcValue``, ``digest``, ``hexdigest``, ``new``, ``copy``.

All run on the active backend's CRC: with the C backend, the builtins of
pyrtu.core._crcfast (csrc/python/rtu_crc_py.c) when that extension is built, else cffi calls.
"""

from __future__ import annotations

from collections.abc import Callable

from pyrtu.core._backend import active
from pyrtu.core._types import BytesLike

_crc16 = active.crc16
# pyrtu.core._crcfast when the C backend runs with it: its builtins are these shapes, with no
# Python frame around them (the call is the whole cost of an 8-byte CRC)
_fast = getattr(active, "CRCFAST", None)
# else the cffi core's bytes entry point (one cffi call, no wrapper frame) for plain bytes
_bytes_crc = getattr(active, "_crc16_bytes", None)


def _crc16_bytes(data: BytesLike) -> bytes:
    """The CRC of ``data`` as its two wire bytes, low byte first."""
    if _bytes_crc is not None and type(data) is bytes:
        return _bytes_crc(data, len(data), 0xFFFF).to_bytes(2, "little")  # type: ignore[no-any-return]
    return _crc16(data).to_bytes(2, "little")  # type: ignore[no-any-return]


def _crc16_swapped(data: BytesLike) -> int:
    """The CRC of ``data`` byte-swapped: ``crc16_swapped(d).to_bytes(2, "big")`` is
    ``crc16_bytes(d)``."""
    if _bytes_crc is not None and type(data) is bytes:
        crc: int = _bytes_crc(data, len(data), 0xFFFF)
    else:
        crc = _crc16(data)
    return ((crc & 0xFF) << 8) | (crc >> 8)


#: The CRC of ``data`` as its two wire bytes, low byte first.
crc16_bytes: Callable[[BytesLike], bytes] = _crc16_bytes if _fast is None else _fast.crc16_bytes
#: The CRC of ``data`` byte-swapped: ``crc16_swapped(d).to_bytes(2, "big")`` is
#: ``crc16_bytes(d)``.
crc16_swapped: Callable[[BytesLike], int] = _crc16_swapped if _fast is None else _fast.crc16_swapped


class Crc16:
    """CRC-16/MODBUS shaped as crcmod's ``Crc`` object (poly 0x18005, reflected,
    initial 0xFFFF, no final XOR), so that code written against
    ``crcmod.predefined.Crc("modbus")`` runs unchanged.

    ``crcValue`` is the CRC as an integer (the low byte goes first on the wire);
    ``digest()`` is crcmod's big-endian bytes of it.
    """

    digest_size = 2
    poly = 0x18005
    reverse = True
    initCrc = 0xFFFF
    xorOut = 0x0000

    __slots__ = ("crcValue",)

    def __init__(self, arg: BytesLike | None = None) -> None:
        self.crcValue: int = 0xFFFF
        if arg is not None:
            self.update(arg)

    def update(self, data: BytesLike) -> None:
        """Add ``data`` to the CRC."""
        self.crcValue = _crc16(data, self.crcValue)

    def new(self, arg: BytesLike | None = None) -> Crc16:
        """A fresh CRC object of the same kind, fed ``arg`` when given."""
        return Crc16(arg)

    def copy(self) -> Crc16:
        """An independent copy holding the same CRC so far."""
        other = Crc16()
        other.crcValue = self.crcValue
        return other

    def digest(self) -> bytes:
        """The CRC value as big-endian bytes (crcmod's order)."""
        return self.crcValue.to_bytes(2, "big")

    def hexdigest(self) -> str:
        """``digest()`` as upper-case hex, as crcmod gives it."""
        return f"{self.crcValue:04X}"

    def __repr__(self) -> str:
        return f"<Crc16 CRC-16/MODBUS crcValue=0x{self.crcValue:04X}>"
