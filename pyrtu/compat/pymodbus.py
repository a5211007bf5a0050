"""pyrtu's C framer and CRC inside pymodbus: one line for an existing program.

    import pyrtu.compat.pymodbus
    pyrtu.compat.pymodbus.install()                 # every RTU client and server created after
    pyrtu.compat.pymodbus.install(device_ids={1})   # a server sharing its bus with other slaves

`PyrtuFramerRTU` subclasses pymodbus's ``FramerRTU`` (its transaction manager checks
``isinstance(framer, FramerRTU)``) and frames with pyrtu's framer core: lengths
predicted from the function code, the CRC in C, garbage and other devices' frames
skipped by their length, exception answers, vendor length rules (``rules=``).  Only
the bytes of what it returns (and of what comes before it) are reported used, so a
second frame in the same read stays in pymodbus's buffer instead of being dropped.

``install()`` registers it in ``pymodbus.framer.FRAMER_NAME_TO_CLASS`` (where pymodbus
clients and servers look their framer up when they are created) and replaces
``FramerRTU.compute_CRC``/``check_CRC`` by the C CRC; ``use(client_or_server)`` puts
it in one client or server only.  ASCII, socket and TLS framers are untouched.
Tested with the pymodbus releases in ``pyrtu.compat.PYMODBUS_RELEASES`` (3.9 to 3.16);
versions outside ``pyrtu.compat.TESTED`` are refused.  What differs between those
releases and matters here is in one table, `API`.  See docs/COMPAT.md.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any, ClassVar

from pyrtu.core import _backend
from pyrtu.core._backend import active
from pyrtu.core.crcshapes import crc16_swapped
from pyrtu.core.frames import FrameKind
from pyrtu.core.rules import RuleTable, check_rules

from ._guard import parse_version, require

#: the pymodbus version found (checked against pyrtu.compat.TESTED before importing it)
VERSION = require("pymodbus")

#: What changed in pymodbus's API between the tested releases (3.9 .. 3.16) that the
#: drop-in meets: feature -> (first version with it, first version without it).
API: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    # the transaction manager calls ``framer.handleFrame(data, exp_devid, exp_tid)``
    # (3.10, pymodbus #2600's release); 3.9 calls ``processIncomingFrame(data)``
    "handle_frame": ((3, 10), (4,)),
    # ``ModbusIOException(text, function_code, *, transaction_id=, dev_id=)``; before
    # 3.15 it takes no ids
    "io_exception_ids": ((3, 15), (4,)),
    # a ModbusSerialServer with ``allow_multiple_devices=True`` calls
    # ``framer.setMultidrop(device_ids)`` on each connection's framer (3.12 to 3.15)
    "set_multidrop": ((3, 12), (3, 16)),
    # the asyncio serial transport empties its receive buffer when two reads are 3
    # characters apart (``ModbusProtocol.inter_frame_time``, 3.12 only): the start of
    # a frame that arrives in chunks (any USB adapter, a loaded machine) is lost
    # before a framer sees it; with pyrtu's framer, which frames by length, it is kept
    "gap_clears_buffer": ((3, 12), (3, 13)),
}
_RELEASE = parse_version(VERSION)
#: feature -> whether the installed pymodbus has it (from `API`)
HAS: dict[str, bool] = {name: low <= _RELEASE < high for name, (low, high) in API.items()}

from pymodbus.client.base import ModbusBaseClient, ModbusBaseSyncClient  # noqa: E402
from pymodbus.exceptions import ModbusIOException  # noqa: E402
from pymodbus.framer import FRAMER_NAME_TO_CLASS, FramerRTU, FramerType  # noqa: E402
from pymodbus.pdu import DecodePDU, ModbusPDU  # noqa: E402
from pymodbus.pdu.register_message import ReadHoldingRegistersRequest  # noqa: E402
from pymodbus.server.base import ModbusBaseServer  # noqa: E402
from pymodbus.transport import ModbusProtocol  # noqa: E402

__all__ = [
    "API",
    "HAS",
    "VERSION",
    "PyrtuFramerRTU",
    "framer_class",
    "install",
    "installed",
    "patched",
    "uninstall",
    "use",
]

_REQUEST = int(FrameKind.REQUEST)
_UNKNOWN = int(FrameKind.UNKNOWN)
_RESPONSE = int(FrameKind.RESPONSE)
_EXCEPTION = int(FrameKind.EXCEPTION)
#: function codes whose answer may repeat the request byte for byte (Application
#: Protocol V1.1b 6.5, 6.6, 6.8, 6.15, 6.16)
_ECHOED = frozenset((5, 6, 8, 21, 22))
# Each call frames the bytes pymodbus holds as one burst (no silence inside it), then,
# when that leaves bytes unresolved, closes them as a silence would: times are fixed.
_NOW_US = 1 << 40
_CLOSED_US = _NOW_US + (1 << 40)


def _core(role: str, rules: RuleTable | None, backend: str | None) -> Any:
    return _backend.backend(backend).Framer(role, rules=rules)._core


def _decodes_requests(decoder: DecodePDU) -> bool:
    """Whether ``decoder`` is a server's (``DecodePDU(True)``): it maps function code 3
    to the request class (every tested release; ``pdu_inx`` exists from 3.11 only)."""
    return decoder.lookupPduClass(b"\x00\x03") is ReadHoldingRegistersRequest


def _undecodable(address: int) -> ModbusIOException:
    """The error pymodbus's own framer raises for a frame its decoder refuses."""
    if HAS["io_exception_ids"]:
        return ModbusIOException("Unable to decode request", transaction_id=0, dev_id=address)
    return ModbusIOException("Unable to decode request")


class PyrtuFramerRTU(FramerRTU):
    """pymodbus's RTU framer, framing with pyrtu's core (C when it is built).

    In a client (pyrtu's ``master`` role) it takes the answer to the request it framed
    last: a frame from the addressed device with that function code (or its exception),
    skipping anything else on the line (an echo of the request, another device's
    frames, garbage, a bad frame before a good retransmission).  In a server (the
    ``slave`` role) it takes requests, to any address or, with ``device_ids``, to those
    and broadcasts only: other devices' requests and their answers are skipped by
    length.  ``counters`` counts frames taken, frames skipped and bytes discarded.
    """

    #: the addresses a server answers (None: all); set by framer_class()/install()
    device_ids: ClassVar[frozenset[int] | None] = None
    #: vendor length rules (pyrtu.core.rules), passed to the framer core
    rules: ClassVar[RuleTable | None] = None
    #: the pyrtu backend ("c" or "python"; None: the active one)
    backend: ClassVar[str | None] = None

    def __init__(self, decoder: DecodePDU) -> None:
        super().__init__(decoder)
        self.is_server = _decodes_requests(decoder)
        #: the addresses this framer's server answers (None: all)
        self.answers: frozenset[int] | None = self.device_ids
        self._core = _core("slave" if self.is_server else "master", self.rules, self.backend)
        self._request = b""  # client: the last request framed (the answer's context)
        self._function = 0
        self._context = b""  # server: the last other device's request (its answer follows)
        self.counters = {"frames": 0, "skipped": 0, "discarded": 0}

    # ------------------------------------------------------------ pymodbus API

    def encode(self, payload: bytes, device_id: int, _tid: int) -> bytes:
        """The ADU: address, PDU, CRC (low byte first)."""
        adu: bytes = active.add_crc(bytes((device_id,)) + payload)
        if not self.is_server:
            self._request = adu
            self._function = payload[0] if payload else 0
        return adu

    def decode(self, data: bytes) -> tuple[int, int, int, bytes]:
        """The first frame or discarded run at the head of ``data``, as pymodbus's
        ``FramerBase.decode``: (bytes used, device id, 0, PDU); (used, 0, 0, b"") for
        bytes discarded; (0, 0, 0, b"") to read more."""
        core = self._core
        core.reset()
        core.feed(data, _NOW_US)
        ev = core.poll()
        if ev is None:  # what a silence after the bytes would resolve
            core.handle_timer(_CLOSED_US)
            ev = core.poll()
            if ev is None:
                return 0, 0, 0, self.EMPTY
            if ev[3]:  # discarded for good only when a good frame follows
                after = core.poll()
                if after is None or after[3]:
                    return 0, 0, 0, self.EMPTY
        adu = ev[6]
        if ev[3]:
            return ev[1], 0, 0, self.EMPTY
        return ev[1], adu[0], 0, adu[1:-2]

    def handleFrame(
        self, data: bytes, exp_devid: int, exp_tid: int
    ) -> tuple[int, ModbusPDU | None]:
        """Frame ``data`` (what pymodbus holds): (bytes used, the PDU taken or None).

        Bytes are used up to the end of the frame taken, or of the last frame or
        garbage skipped; an incomplete frame at the end stays for the next read."""
        core = self._core
        if self.is_server:
            core.reset()
            if self._context:  # the request before: its answer is told by its length
                core.feed(self._context, _NOW_US)  # (kept until a frame follows it)
                ev = core.poll()
                if ev is None or ev[3] or ev[1] != len(self._context):
                    core.reset()
                    self._context = b""
        else:
            core.expect(self._request)
        used = 0
        pos = 0
        n = len(data)
        while pos < n:
            took = core.feed(data[pos:] if pos else data, _NOW_US)
            pos += took
            while (ev := core.poll()) is not None:
                used += ev[1]
                if (pdu := self._event(ev, exp_devid)) is not None:
                    return used, pdu
            if took == 0:  # the core's buffer is full of unresolved bytes: close them
                core.handle_timer(_CLOSED_US)
        if used < n:  # bytes left unresolved: what a silence after them would resolve
            core.handle_timer(_CLOSED_US)
            closed = used
            while (ev := core.poll()) is not None:
                closed += ev[1]
                if ev[3]:
                    continue
                used = closed  # a good frame: what precedes it cannot complete
                if (pdu := self._event(ev, exp_devid)) is not None:
                    return used, pdu
        return used, None

    def processIncomingFrame(self, data: bytes) -> tuple[int, ModbusPDU | None]:
        """pymodbus 3.9's entry point (`API` "handle_frame"): `handleFrame` for the
        device the last request went to (a server: any of its ``device_ids``)."""
        expected = self._request[0] if self._request and not self.is_server else 0
        return self.handleFrame(data, expected, 0)

    def setMultidrop(self, device_ids: list[int]) -> None:
        """pymodbus 3.12 to 3.15 (`API` "set_multidrop"): a server created with
        ``allow_multiple_devices=True`` gives its devices; they are the addresses
        answered unless ``device_ids`` was set by `framer_class`/`install`."""
        if self.device_ids is None and device_ids:
            self.answers = frozenset(device_ids)

    # ------------------------------------------------------------ internals

    def _event(self, ev: tuple[Any, ...], exp_devid: int) -> ModbusPDU | None:
        """A core event: the PDU when it is the frame to take, else None (counted)."""
        length, kind, error, adu = ev[1], ev[2], ev[3], ev[6]
        c = self.counters
        if error:
            c["discarded"] += length
            return None
        address = adu[0]
        if self.is_server:
            ids = self.answers
            wanted = (kind == _REQUEST or kind == _UNKNOWN) and (
                ids is None or address == 0 or address in ids
            )
            # another device's request: its answer comes next, told by its length
            self._context = adu if kind == _REQUEST and not wanted else b""
        else:
            wanted = (
                (kind == _RESPONSE or kind == _EXCEPTION or kind == _UNKNOWN)
                and (not exp_devid or address == exp_devid)
                and (not self._function or adu[1] & 0x7F == self._function)
                # the echo of the request (an echoing adapter, a stale echo) is not its
                # answer, unless the answer is the request itself (FC 5, 6, 8, 21, 22)
                and (adu != self._request or self._function in _ECHOED)
            )
        if not wanted:
            c["skipped"] += 1
            return None
        pdu = self.decoder.decode(adu[1:-2])
        if pdu is None:
            raise _undecodable(address)
        c["frames"] += 1
        pdu.dev_id = address
        pdu.transaction_id = 0
        return pdu


def framer_class(
    device_ids: Iterable[int] | None = None,
    rules: RuleTable | None = None,
    backend: str | None = None,
) -> type[PyrtuFramerRTU]:
    """A `PyrtuFramerRTU` class answering ``device_ids`` (None: every address) with
    the vendor length ``rules`` on pyrtu's ``backend`` ("c", "python"; None: the
    active one); what ``install``/``use`` register."""
    ids: frozenset[int] | None = None
    if device_ids is not None:
        if isinstance(device_ids, int):
            device_ids = (device_ids,)
        ids = frozenset(device_ids)
        for i in ids:
            if isinstance(i, bool) or not isinstance(i, int):
                raise TypeError(f"device_ids must be integers, not {type(i).__name__}")
            if not 1 <= i <= 247:
                raise ValueError(f"device_ids must be 1..247 (Modbus serial addresses), not {i}")
        if not ids:
            raise ValueError("device_ids must name at least one device (None: all)")
    if rules is not None:
        if not isinstance(rules, Mapping):
            raise TypeError(
                f"rules must be a mapping (pyrtu.core.rules), not {type(rules).__name__}"
            )
        check_rules(rules)  # TypeError/ValueError naming the bad entry
    if backend is not None:
        _backend.backend(backend)  # ValueError/ImportError for a backend that cannot run
    if ids is None and rules is None and backend is None:
        return PyrtuFramerRTU
    name = "PyrtuFramerRTU" if ids is None else f"PyrtuFramerRTU{sorted(ids)}"
    attrs = {"device_ids": ids, "rules": rules, "backend": backend}
    return type(name, (PyrtuFramerRTU,), attrs)


class _InterFrameTime:
    """``ModbusProtocol.inter_frame_time`` on pymodbus 3.12 (`API` "gap_clears_buffer"):
    0 (no clearing on a gap) where pyrtu's framer frames, the transport's own value
    everywhere else."""

    def __get__(self, protocol: object, owner: type | None = None) -> float:
        if protocol is None:
            return 0.0
        state = vars(protocol)
        if isinstance(state.get("framer"), PyrtuFramerRTU):
            return 0.0
        value: float = state.get("_stock_inter_frame_time", 0.0)
        return value

    def __set__(self, protocol: object, value: float) -> None:
        vars(protocol)["_stock_inter_frame_time"] = value


def _keep_chunked_frames() -> None:
    """On pymodbus 3.12, let transports framed by pyrtu keep bytes across read gaps
    (once; transports framed by pymodbus's framers keep their behaviour)."""
    if HAS["gap_clears_buffer"] and not isinstance(
        ModbusProtocol.__dict__.get("inter_frame_time"), _InterFrameTime
    ):
        ModbusProtocol.inter_frame_time = _InterFrameTime()  # type: ignore[attr-defined]


_saved: dict[str, Any] = {}


def _compute_crc(cls: type[FramerRTU], data: bytes) -> int:
    """FramerRTU.compute_CRC in C: the CRC byte-swapped (``to_bytes(2, "big")`` is
    the wire order)."""
    return crc16_swapped(data)


def _check_crc(cls: type[FramerRTU], data: bytes, check: int) -> bool:
    """FramerRTU.check_CRC in C."""
    return crc16_swapped(data) == check


def install(
    device_ids: Iterable[int] | None = None,
    rules: RuleTable | None = None,
    backend: str | None = None,
) -> type[PyrtuFramerRTU]:
    """Make every pymodbus RTU client and server created from now on frame with
    pyrtu (``device_ids``: the addresses a server answers; None: all), and
    ``FramerRTU.compute_CRC``/``check_CRC`` compute in C.  Returns the framer class.
    Installing again replaces the settings."""
    cls = framer_class(device_ids, rules, backend)
    _keep_chunked_frames()
    if not _saved:
        _saved["framer"] = FRAMER_NAME_TO_CLASS[FramerType.RTU]
        _saved["compute_CRC"] = FramerRTU.__dict__["compute_CRC"]
        _saved["check_CRC"] = FramerRTU.__dict__["check_CRC"]
    FRAMER_NAME_TO_CLASS[FramerType.RTU] = cls
    FramerRTU.compute_CRC = classmethod(_compute_crc)  # type: ignore[assignment,method-assign]
    FramerRTU.check_CRC = classmethod(_check_crc)  # type: ignore[assignment,method-assign]
    return cls


def uninstall() -> None:
    """Undo `install`: pymodbus's own framer and CRC for what is created from now on."""
    if not _saved:
        return
    FRAMER_NAME_TO_CLASS[FramerType.RTU] = _saved.pop("framer")
    FramerRTU.compute_CRC = _saved.pop("compute_CRC")  # type: ignore[method-assign]
    FramerRTU.check_CRC = _saved.pop("check_CRC")  # type: ignore[method-assign]


def installed() -> bool:
    """Whether `install` is in effect."""
    return bool(_saved)


@contextmanager
def patched(
    device_ids: Iterable[int] | None = None,
    rules: RuleTable | None = None,
    backend: str | None = None,
) -> Iterator[type[PyrtuFramerRTU]]:
    """`install` for a ``with`` block (what was in effect before comes back after)."""
    before = FRAMER_NAME_TO_CLASS[FramerType.RTU] if _saved else None
    cls = install(device_ids, rules, backend)
    try:
        yield cls
    finally:
        if before is None:
            uninstall()
        else:
            FRAMER_NAME_TO_CLASS[FramerType.RTU] = before


def use(
    target: ModbusBaseClient | ModbusBaseSyncClient | ModbusBaseServer,
    device_ids: Iterable[int] | None = None,
    rules: RuleTable | None = None,
    backend: str | None = None,
) -> PyrtuFramerRTU | type[PyrtuFramerRTU]:
    """Put pyrtu's framer in one RTU client (sync or asyncio; returns the framer) or
    one server (before it serves; returns the class its connections will use)."""
    cls = framer_class(device_ids, rules, backend)
    _keep_chunked_frames()
    if isinstance(target, ModbusBaseServer):
        if not (isinstance(target.framer, type) and issubclass(target.framer, FramerRTU)):
            raise ValueError(f"use: the server frames with {target.framer!r}, not RTU")
        target.framer = cls
        return cls
    if device_ids is not None:
        raise ValueError("use: device_ids is for a server (a client takes the answer it asked)")
    if isinstance(target, ModbusBaseSyncClient):
        old = target.framer
        if not isinstance(old, FramerRTU):
            raise ValueError(f"use: the client frames with {type(old).__name__}, not RTU")
        new = cls(old.decoder)
        target.framer = target.transaction.framer = new
        return new
    if isinstance(target, ModbusBaseClient):
        old = target.ctx.framer
        if not isinstance(old, FramerRTU):
            raise ValueError(f"use: the client frames with {type(old).__name__}, not RTU")
        new = cls(old.decoder)
        target.ctx.framer = new
        return new
    raise TypeError(f"use: a pymodbus client or server, not {type(target).__name__}")
