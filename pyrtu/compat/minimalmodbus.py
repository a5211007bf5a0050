"""pyrtu's C CRC inside minimalmodbus: one line for an existing program.

    import pyrtu.compat.minimalmodbus
    pyrtu.compat.minimalmodbus.install()

minimalmodbus looks its CRC function up as the module attribute
``minimalmodbus._calculate_crc`` at call time (building requests, checking answers);
``install()`` replaces it by `pyrtu.crc16_bytes` (the two CRC bytes, low byte first,
as minimalmodbus returns them).  Framing stays minimalmodbus's: it frames in the
private ``Instrument._communicate`` and offers no hook.  Tested with the minimalmodbus
versions in ``pyrtu.compat.TESTED``; others are refused.
"""

from __future__ import annotations

from pyrtu.core.crcshapes import crc16_bytes

from ._guard import require
from ._patch import Patches, crc_adapter_api

VERSION = require("minimalmodbus")

import minimalmodbus as _mm  # noqa: E402

__all__ = ["VERSION", "install", "installed", "patched", "uninstall"]

_patches = Patches("minimalmodbus")


def _calculate_crc(inputbytes: bytes) -> bytes:
    """minimalmodbus's ``_calculate_crc`` in C: the CRC, low byte first."""
    if not isinstance(inputbytes, bytes):
        raise TypeError(
            f"The CRC input bytes should be bytes. Given: {inputbytes!r}"  # as minimalmodbus
        )
    return crc16_bytes(inputbytes)


def install() -> None:
    """minimalmodbus computes and checks its CRCs with pyrtu's CRC from now on."""
    _patches.apply([(_mm, "_calculate_crc", _calculate_crc)])


uninstall, installed, patched = crc_adapter_api(_patches, install)
