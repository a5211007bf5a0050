"""pyrtu's C CRC and framer inside modbus_tk.

    import pyrtu.compat.modbus_tk
    pyrtu.compat.modbus_tk.install()                  # CRC in C
    pyrtu.compat.modbus_tk.install(device_ids={1})    # and its RTU server framed by pyrtu

modbus_tk computes its CRC with ``modbus_tk.utils.calculate_crc`` (the CRC as an
integer, bytes swapped), looked up at call time; ``install()`` replaces it by
`pyrtu.crc16_swapped`.

modbus_tk's ``RtuServer`` reads until a silence and hands the bytes to its
``modbus_rtu.RtuServer.after_read`` hook, which may replace them.  With
``device_ids`` (or ``framing=True``), ``install`` adds a hook that frames those bytes
with pyrtu (length prediction and CRC) and hands modbus_tk the first request for one
of ``device_ids`` (every address when None), so a noise byte before the request, or
another slave's frames read with it, no longer spoil it.  modbus_tk's master reads
the number of bytes it expects and stops, so a noise byte before an answer costs its
last byte before any hook sees it: that side is left as modbus_tk has it.
Tested with the modbus_tk versions in ``pyrtu.compat.TESTED``; others are refused.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from pyrtu.core._backend import active
from pyrtu.core.crcshapes import crc16_swapped
from pyrtu.core.frames import FrameKind

from ._guard import require
from ._patch import Patches

VERSION = require("modbus_tk")

from modbus_tk import hooks as _hooks  # noqa: E402
from modbus_tk import utils as _utils  # noqa: E402

__all__ = ["VERSION", "install", "installed", "patched", "request_hook", "uninstall"]

_patches = Patches("modbus_tk")
_HOOK = "modbus_rtu.RtuServer.after_read"
_hook_installed: list[Any] = []


#: modbus_tk's ``utils.calculate_crc`` in C: the CRC with its bytes swapped
calculate_crc = crc16_swapped


def request_hook(device_ids: Iterable[int] | None = None) -> Any:
    """An ``after_read`` hook for modbus_tk's RtuServer: the first request (to one of
    ``device_ids``, or any) framed by pyrtu in the bytes read, or None (modbus_tk then
    handles the bytes as read)."""
    ids = None if device_ids is None else frozenset(device_ids)
    parse = active.parse_stream

    def after_read(args: tuple[Any, bytes]) -> bytes | None:
        _server, request = args
        for frame in parse(bytes(request), "slave"):
            if frame.error is None and frame.kind is FrameKind.REQUEST:
                if ids is None or frame.address == 0 or frame.address in ids:
                    return frame.adu if frame.adu != request else None
        return None

    return after_read


def install(device_ids: Iterable[int] | None = None, framing: bool | None = None) -> None:
    """modbus_tk computes its CRCs with pyrtu from now on; with ``device_ids`` or
    ``framing=True`` its RTU servers' requests are framed by pyrtu too."""
    uninstall()
    _patches.apply([(_utils, "calculate_crc", calculate_crc)])
    if framing or (framing is None and device_ids is not None):
        hook = request_hook(device_ids)
        _hooks.install_hook(_HOOK, hook)
        _hook_installed.append(hook)


def uninstall() -> None:
    """modbus_tk's own CRC and framing again."""
    _patches.undo()
    while _hook_installed:
        _hooks.uninstall_hook(_HOOK, _hook_installed.pop())


def installed() -> bool:
    return _patches.active


@contextmanager
def patched(device_ids: Iterable[int] | None = None, framing: bool | None = None) -> Iterator[None]:
    """`install` for a ``with`` block."""
    install(device_ids, framing)
    try:
        yield
    finally:
        uninstall()
