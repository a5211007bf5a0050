"""pyrtu: a Modbus RTU toolkit whose hot path is C.

The backend is chosen once, by `pyrtu.core._backend` at import: the C core when it is
built, else the pure-Python twin; this package re-exports its names.
``PYRTU_PURE=1`` forces the twin; ``PYRTU_REQUIRE_C=1`` makes
the import fail when the C core is missing.  ``pyrtu.BACKEND`` says which runs;
``pyrtu.backend(name)`` returns either one (both expose the same names).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pyrtu import _startup  # noqa: F401  (first: Ctrl-C while the pyrtu command starts)
from pyrtu.core import _backend
from pyrtu.core._lazy import lazy_attributes
from pyrtu.core.ascii import decode_ascii, encode_ascii
from pyrtu.core.crcshapes import Crc16, crc16_bytes, crc16_swapped
from pyrtu.core.frames import ErrorReason, Frame, FrameKind, FrameList
from pyrtu.core.line import LineConfig
from pyrtu.core.rules import BONFIGLIOLI, CV100, LengthRule
from pyrtu.core.timing import Timing

from ._version import __version__ as __version__

_active = _backend.active
_C = _backend.C

BACKEND: str = _active.BACKEND
crc16 = _active.crc16
add_crc = _active.add_crc
check_crc = _active.check_crc
lrc = _active.lrc
crc16_paths = _active.crc16_paths
crc16_path = _active.crc16_path
char_timing = _active.char_timing
Framer = _active.Framer
parse_stream = _active.parse_stream

# Modbus TCP: MBAP framing (Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3)
from pyrtu.core.mbap import MbapError, MbapFrame, MbapFrameList  # noqa: E402

MbapFramer = _active.MbapFramer
parse_tcp_stream = _active.parse_tcp_stream
encode_mbap = _active.encode_mbap


# The thin API over the core: imported after the backend is chosen (they use it).
from pyrtu.drivers.master import Master  # noqa: E402
from pyrtu.drivers.slave import Slave  # noqa: E402
from pyrtu.pdu.data import (  # noqa: E402
    decode_float32,
    decode_int32,
    decode_string,
    decode_uint32,
    decode_values,
    encode_float32,
    encode_int32,
    encode_string,
    encode_uint32,
    encode_values,
)
from pyrtu.pdu.errors import (  # noqa: E402
    EXCEPTION_NAMES,
    BusFault,
    ExceptionResponseError,
    FrameError,
    ModbusError,
    NoResponseError,
    PortError,
    SlaveException,
)
from pyrtu.protocol.datastore import DataStore, Table  # noqa: E402

from .pdu import CommEventLog  # noqa: E402

backend = _backend.backend
available_backends = _backend.available_backends

if TYPE_CHECKING:
    from .drivers.aio import AsyncMaster
    from .drivers.aio_slave import AsyncSlave
    from .poller import Poller

#: names loaded on first use (their modules import asyncio), and their homes
_LAZY = {
    "Poller": "pyrtu.poller",
    "AsyncMaster": "pyrtu.drivers.aio",
    "AsyncSlave": "pyrtu.drivers.aio_slave",
}


#: ``pyrtu.Poller``, ``pyrtu.AsyncMaster``, ``pyrtu.AsyncSlave`` and the submodules
#: (``pyrtu.data``, ``pyrtu.aio``, ...) on first use: ``import pyrtu`` loads neither the
#: poller nor asyncio, and the paths the documentation shows work after it alone
__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = [
    "BACKEND",
    "BONFIGLIOLI",
    "CV100",
    "EXCEPTION_NAMES",
    "AsyncMaster",
    "AsyncSlave",
    "BusFault",
    "CommEventLog",
    "Crc16",
    "DataStore",
    "ErrorReason",
    "ExceptionResponseError",
    "Frame",
    "FrameError",
    "FrameKind",
    "FrameList",
    "Framer",
    "LengthRule",
    "LineConfig",
    "Master",
    "MbapError",
    "MbapFrame",
    "MbapFrameList",
    "MbapFramer",
    "ModbusError",
    "NoResponseError",
    "Poller",
    "PortError",
    "Slave",
    "SlaveException",
    "Table",
    "Timing",
    "add_crc",
    "available_backends",
    "backend",
    "char_timing",
    "check_crc",
    "crc16",
    "crc16_bytes",
    "crc16_path",
    "crc16_paths",
    "crc16_swapped",
    "decode_ascii",
    "decode_float32",
    "decode_int32",
    "decode_string",
    "decode_uint32",
    "decode_values",
    "encode_ascii",
    "encode_float32",
    "encode_int32",
    "encode_mbap",
    "encode_string",
    "encode_uint32",
    "encode_values",
    "lrc",
    "parse_stream",
    "parse_tcp_stream",
]
