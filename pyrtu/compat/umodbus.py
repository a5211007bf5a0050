"""pyrtu's C CRC and framer inside umodbus.

    import pyrtu.compat.umodbus
    pyrtu.compat.umodbus.install()          # CRC in C for umodbus's RTU client and server

umodbus computes its CRC in ``umodbus.client.serial.redundancy_check`` (``get_crc``,
``validate_crc``) and imports both by name into its RTU client
(``umodbus.client.serial.rtu``) and server (``umodbus.server.serial.rtu``);
``install()`` replaces them in all three modules.

umodbus's ``RTUServer`` frames by silence: one ``read(256)`` ended by the inter-byte
timeout is one request, so a leading noise byte, two frames in one read or another
slave's answer on a shared bus spoil the request.  `PyrtuRTUServer` is the same
server (umodbus's routes, ``process`` and ``respond``) whose ``serve_once`` frames
with pyrtu's framer: requests found by length and CRC, garbage and other devices'
frames skipped; ``device_ids`` limits it to its own addresses on a shared bus::

    server = get_server(PyrtuRTUServer, serial_port)     # umodbus.server.serial.get_server
    server.device_ids = {1}

Tested with the umodbus versions in ``pyrtu.compat.TESTED``; others are refused.
"""

from __future__ import annotations

import time
from typing import Any

from pyrtu.core._backend import active
from pyrtu.core.crcshapes import crc16_bytes
from pyrtu.core.frames import FrameKind

from ._guard import require
from ._patch import Patches, crc_adapter_api

VERSION = require("umodbus")

from umodbus.client.serial import redundancy_check as _rc  # noqa: E402
from umodbus.client.serial import rtu as _client_rtu  # noqa: E402
from umodbus.server.serial import rtu as _server_rtu  # noqa: E402

__all__ = ["VERSION", "PyrtuRTUServer", "install", "installed", "patched", "uninstall"]

_patches = Patches("umodbus")
_crc16 = active.crc16


#: umodbus's ``get_crc`` in C: the CRC, low byte first
get_crc = crc16_bytes


def validate_crc(msg: bytes) -> None:
    """umodbus's ``validate_crc`` in C: raises its ``CRCError`` for a bad CRC."""
    if len(msg) < 2 or _crc16(msg) != 0:  # the CRC over a frame and its CRC is 0
        raise _rc.CRCError("CRC validation failed.")


def install() -> None:
    """umodbus's RTU client and server compute and check CRCs with pyrtu from now on."""
    _patches.apply(
        [
            (module, name, new)
            for module in (_rc, _client_rtu, _server_rtu)
            for name, new in (("get_crc", get_crc), ("validate_crc", validate_crc))
        ]
    )


uninstall, installed, patched = crc_adapter_api(_patches, install)


class PyrtuRTUServer(_server_rtu.RTUServer):  # type: ignore[misc]
    """umodbus's RTU server, its requests framed by pyrtu (length prediction, CRC;
    a silence ends only what nothing predicts).  ``device_ids``: the addresses it
    answers (None: every request, as umodbus does); broadcasts are served, unanswered."""

    device_ids: frozenset[int] | set[int] | None = None
    _framer: Any = None

    def serve_once(self) -> None:
        """Read what the port has (up to its timeout), answer each request found."""
        port = self.serial_port
        framer = self._framer
        if framer is None:
            framer = self._framer = active.Framer(
                "slave",
                baudrate=port.baudrate,
                parity="N" if port.parity == "N" else port.parity,
                stopbits=port.stopbits,
                bytesize=port.bytesize,
            )
        data = port.read(max(1, port.in_waiting))
        now = time.monotonic()
        if data:
            framer.receive_data(data, now)
        else:
            framer.handle_timer(now)
        while (frame := framer.next_event()) is not None:
            if frame.error is not None or frame.kind is not FrameKind.REQUEST:
                continue
            ids = self.device_ids
            if ids is not None and frame.address != 0 and frame.address not in ids:
                continue
            response = self.process(frame.adu)
            if frame.address != 0:  # a broadcast is executed, never answered
                self.respond(response)
                framer.send(response)
        if not data:
            raise ValueError  # what umodbus's serve_forever takes for "nothing read"
