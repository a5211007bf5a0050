"""The C backend: the names of the pure-Python twin over the cffi module.

Imported by pyrtu/core/_backend.py's backend selection (and bench/bench_crc.py's C-only
rows), nowhere else in the package; ImportError when the extension was not built.
Buffers reach C through ``ffi.from_buffer`` (no copy).
crc16, add_crc and check_crc are the builtins of pyrtu.core._crcfast when that extension
is built (a cffi call costs about ten times a builtin's), else cffi calls.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

from pyrtu.core._rtu_core import ffi, lib
from pyrtu.core._types import BACKEND_NAMES, BytesLike, crc_seed
from pyrtu.core.frames import FrameList, LazyFrames
from pyrtu.core.framing import Event, as_bytes, backend_framing, check_core_limits, counters_dict
from pyrtu.core.mbap import MbapEvent, MbapFrameList, backend_mbap, mbap_counters_dict
from pyrtu.core.options import CoreOptions, flush_us_for
from pyrtu.core.timing import Timing

BACKEND = "c"
#: the POSIX I/O of the core (csrc/rtu_*_io.c: the exchange thread, the bus's I/O loop) is
#: built; False on Windows (pyrtu/core/_build_core.py), where the twin's take over
POSIX_IO: bool = hasattr(lib, "rtu_xfer_io_run") and hasattr(lib, "rtu_vbus_io_run")
NO_TIME = -(2**63)
INT64_MAX = 2**63 - 1

__all__ = [*BACKEND_NAMES, "CRCFAST", "POSIX_IO", "ffi", "lib"]

_PATHS = {
    "bytewise": lib.RTU_CRC_BYTEWISE,
    "slice8": lib.RTU_CRC_SLICE8,
    "clmul": lib.RTU_CRC_CLMUL,
    "vclmul": lib.RTU_CRC_VCLMUL,
}


def _buffer(data: BytesLike, name: str) -> Any:
    """A C view of any buffer; strided ones are copied (as the twin reads them)."""
    try:
        return ffi.from_buffer("uint8_t[]", data)
    except TypeError:
        raise TypeError(f"{name} must be a bytes-like object, not {type(data).__name__}") from None
    except BufferError:  # not C-contiguous
        return ffi.from_buffer("uint8_t[]", memoryview(data).tobytes())


_crc16_bytes = lib.rtu_crc16_bytes
_crc16 = lib.rtu_crc16


# The CRC through cffi: the functions of this backend when pyrtu.core._crcfast is not built
# (and the reference the tests hold the builtins to).
def _cffi_crc16(data: BytesLike, crc: int = 0xFFFF) -> int:
    """CRC-16/MODBUS of ``data``, continuing from ``crc`` (0xFFFF to start)."""
    if crc is not True and crc is not False:  # cffi would take a bool as 0 / 1
        try:  # bytes: straight through cffi, which refuses any other type
            return _crc16_bytes(data, len(data), crc)  # type: ignore[no-any-return,arg-type]
        except (TypeError, OverflowError):
            pass
    buf = _buffer(data, "data")
    return int(lib.rtu_crc16(buf, len(buf), crc_seed(crc)))


def _cffi_add_crc(data: BytesLike) -> bytes:
    """``data`` with its CRC appended, low byte first (CFW100 4.2.4)."""
    raw = as_bytes(data)
    crc = _crc16(raw, len(raw), 0xFFFF)
    return raw + bytes((crc & 0xFF, crc >> 8))


def _cffi_check_crc(adu: BytesLike) -> bool:
    """True when the last two bytes of ``adu`` are the CRC of the rest."""
    buf = _buffer(adu, "adu")
    n = len(buf)
    if n < 3:
        return False
    crc = lib.rtu_crc16(buf, n - 2, 0xFFFF)
    return bool(buf[n - 2] == crc & 0xFF and buf[n - 1] == crc >> 8)


def _load_crcfast() -> ModuleType | None:
    """pyrtu.core._crcfast (csrc/python/rtu_crc_py.c): the same CRC as builtins, which cost
    a tenth of a cffi call.  None when it is not built, and with PYRTU_PURE=1 (the twin
    runs; nothing of it is loaded)."""
    if os.environ.get("PYRTU_PURE") == "1":
        return None
    try:
        from pyrtu.core import _crcfast
    except ImportError:
        return None
    return _crcfast


#: the CRC module in use (None: the CRC goes through cffi); chosen once, here
CRCFAST = _load_crcfast()
crc16 = _cffi_crc16 if CRCFAST is None else CRCFAST.crc16
add_crc = _cffi_add_crc if CRCFAST is None else CRCFAST.add_crc
check_crc = _cffi_check_crc if CRCFAST is None else CRCFAST.check_crc


def lrc(data: BytesLike) -> int:
    """LRC of ASCII mode: two's complement of the 8-bit byte sum (seed 004, 6.7.2.3)."""
    buf = _buffer(data, "data")
    return int(lib.rtu_lrc(buf, len(buf)))


def crc16_paths() -> tuple[str, ...]:
    """The CRC implementations this CPU runs."""
    return tuple(name for name, code in _PATHS.items() if lib.rtu_crc16_path_available(code))


def crc16_path(path: str, data: BytesLike, crc: int = 0xFFFF) -> int:
    """CRC through one named implementation (for tests and benchmarks)."""
    if path not in _PATHS:
        raise ValueError(f"crc16_path: unknown path {path!r} (known: {', '.join(_PATHS)})")
    buf = _buffer(data, "data")
    out = ffi.new("uint16_t *")
    status = lib.rtu_crc16_path(_PATHS[path], buf, len(buf), crc_seed(crc), out)
    if status == lib.RTU_EUNSUPPORTED:
        raise ValueError(f"crc16_path: this CPU cannot run the {path!r} path")
    if status != lib.RTU_OK:
        raise ValueError(f"crc16_path: rtu_crc16_path failed with status {status}")
    return int(out[0])


def _initialised(ctype: str, init: Callable[[Any, Any], int], arg: Any, about: object) -> Any:
    """A new C struct (``ctype``, a pointer type) that ``init(struct, arg)`` sets up for
    ``about``; ValueError if the C core refuses (the checks before make that a bug)."""
    struct = ffi.new(ctype)
    status = init(struct, arg)
    if status != lib.RTU_OK:
        raise ValueError(f"cannot initialise {ctype.rstrip(' *')} for {about} (status {status})")
    return struct


def _config(options: CoreOptions) -> Any:
    check_core_limits(options)
    cfg = ffi.new("rtu_config *")
    status = lib.rtu_config_init(cfg, options.role, options.baudrate, options.bits, options.rule)
    if status != lib.RTU_OK:
        raise ValueError(f"cannot configure the framer (status {status}) for {options}")
    if options.t15_us is not None:
        cfg.timing.t15_us = options.t15_us
    if options.t35_us is not None:
        cfg.timing.t35_us = options.t35_us
    cfg.flush_us = flush_us_for(options, int(cfg.timing.t35_us))
    cfg.strict = int(options.strict)
    cfg.max_adu = options.max_adu
    for fc, pair in options.rules.items():
        for direction, rule in enumerate(pair):
            if rule is None:
                continue
            c_rule = ffi.new(
                "rtu_rule *", (rule.type, rule.offset, rule.width, rule.scale, rule.add)
            )
            if (
                lib.rtu_rules_set(ffi.addressof(cfg, "rules"), direction, fc, c_rule[0])
                != lib.RTU_OK
            ):
                raise ValueError(f"rules[{fc}]: the C core refuses {rule!r}")
    return cfg


class _RequestPredictor:
    """``rtu_predict`` over the request rules of a line (see `FramerCore`'s owner,
    `pyrtu.protocol.server`): (RTU_PRED_*, length) for the bytes of a request so far."""

    __slots__ = ("_cfg", "_length", "_rules")

    def __init__(self, options: CoreOptions) -> None:
        self._cfg = _config(options)  # owns the rules the pointer below points into
        self._rules = ffi.addressof(self._cfg, "rules")
        self._length = ffi.new("size_t *")

    def __call__(self, adu: bytes) -> tuple[int, int]:
        self._length[0] = 0  # (what the core leaves for "no rule": 0, as the twin)
        status = lib.rtu_predict(self._rules, lib.RTU_DIR_REQUEST, adu, len(adu), self._length)
        return int(status), int(self._length[0])


def request_predictor(options: CoreOptions) -> Callable[[bytes], tuple[int, int]]:
    """The request-length predictor of ``options``' rules, as the C core predicts."""
    return _RequestPredictor(options)


# bound once: a ``lib.name`` lookup per call costs more than the call (cffi's lib_getattr)
_buffer_of = ffi.buffer
_framer_feed = lib.rtu_framer_feed
_framer_poll = lib.rtu_framer_poll
_framer_event_data = lib.rtu_framer_event_data
_framer_handle_timer = lib.rtu_framer_handle_timer
_framer_deadline = lib.rtu_framer_deadline
_framer_sent = lib.rtu_framer_sent
_framer_reset = lib.rtu_framer_reset
_framer_needed = lib.rtu_framer_needed


class _Core:
    def __init__(self, options: CoreOptions) -> None:
        self.f = _initialised("rtu_framer *", lib.rtu_framer_init, _config(options), options)

    def feed(self, data: bytes, now_us: int) -> int:
        return int(_framer_feed(self.f, data, len(data), now_us))

    def poll(self) -> Event | None:
        f = self.f
        if not _framer_poll(f):
            return None
        e = f.event
        n = e.length
        adu = _buffer_of(_framer_event_data(f), n)[:]  # bytes, one copy
        return (e.offset, n, e.kind, e.error, e.start_us, e.end_us, adu)

    def take(self) -> tuple[int, int, bytes] | None:
        """The next event as (error, end_us, adu): poll() for a client that needs no
        more (fewer reads of the C struct on the master's hot path)."""
        f = self.f
        if not _framer_poll(f):
            return None
        e = f.event
        return (e.error, e.end_us, _buffer_of(_framer_event_data(f), e.length)[:])

    def expect(self, adu: bytes) -> None:
        """reset() then sent(adu): a fresh framer for the answer to ``adu``."""
        f = self.f
        _framer_reset(f)
        _framer_sent(f, adu, len(adu))

    def handle_timer(self, now_us: int) -> None:
        _framer_handle_timer(self.f, now_us)

    def deadline(self) -> int | None:
        deadline = int(_framer_deadline(self.f))
        return None if deadline == INT64_MAX else deadline

    def sent(self, adu: bytes) -> None:
        _framer_sent(self.f, adu, len(adu))

    def reset(self) -> None:
        _framer_reset(self.f)

    def needed(self) -> int:
        return int(_framer_needed(self.f))

    def counts(self) -> tuple[Sequence[int], Sequence[int], int]:
        c = self.f.counters
        return list(c.frames), list(c.discarded), int(c.discard_events)


class _Blocks:
    """Entry ``i`` of a parse spread over C arrays ``[(array, count), ...]``."""

    def __init__(self, blocks: list[tuple[Any, int]]) -> None:
        self._blocks = blocks
        self._starts: list[int] = []
        total = 0
        for _, n in blocks:
            self._starts.append(total)
            total += n

    def __getitem__(self, i: int) -> Any:
        b = len(self._starts) - 1
        while self._starts[b] > i:
            b -= 1
        return self._blocks[b][0][i - self._starts[b]]


def _collect_events(
    ctype: str, cap: int, parse: Callable[[Any, int, Any], int], what: str
) -> list[tuple[Any, int]]:
    """Run a C parser call ``parse(out, cap, n_out)`` into arrays of ``ctype`` until it
    returns RTU_OK, doubling the array (up to 4 Mi entries) while it says RTU_ENOSPC;
    the filled blocks ``(array, count)`` in order."""
    blocks: list[tuple[Any, int]] = []
    n_out = ffi.new("size_t *")
    while True:
        out = ffi.new(ctype, cap)
        status = parse(out, cap, n_out)
        if n_out[0]:
            blocks.append((out, int(n_out[0])))
        if status == lib.RTU_OK:
            return blocks
        if status != lib.RTU_ENOSPC:
            raise ValueError(f"{what} failed with status {status}")
        cap = min(cap * 2, 1 << 22)


class _CEntries(LazyFrames[Any]):
    """A capture's entries in C arrays (the blocks of `_collect_events`); its frames
    are built on access (`CFrameList`, `CMbapFrameList`)."""

    def __init__(
        self, data: bytes, blocks: list[tuple[Any, int]], counters: dict[str, int]
    ) -> None:
        super().__init__(data, sum(n for _, n in blocks))
        self._entries = _Blocks(blocks)
        self.counters = counters


class CFrameList(_CEntries, FrameList):
    """Entries live in C arrays (blocks of rtu_event); frames are built on access."""

    def _entry(self, i: int) -> tuple[int, int, int, int, int | None, int | None]:
        e = self._entries[i]
        return (
            e.offset,
            e.length,
            e.kind,
            e.error,
            None if e.start_us == NO_TIME else e.start_us,
            None if e.end_us == NO_TIME else e.end_us,
        )


def _parse(
    options: CoreOptions, data: bytes, offsets: list[int], times_us: list[int]
) -> CFrameList:
    cfg = _config(options)
    n_chunks = len(offsets)
    c_offsets = ffi.new("uint64_t[]", offsets) if n_chunks else ffi.NULL
    c_times = ffi.new("int64_t[]", times_us) if n_chunks else ffi.NULL
    marks = ffi.new("rtu_mark[]", max(n_chunks, 1))
    n_marks = ffi.new("size_t *")
    status = lib.rtu_marks_from_chunks(
        ffi.addressof(cfg, "timing"), c_offsets, c_times, n_chunks, len(data), marks, n_marks
    )
    if status != lib.RTU_OK:
        raise ValueError(f"parse_stream: chunk times rejected (status {status})")
    parser = _initialised("rtu_parser *", lib.rtu_parser_init, cfg, options)
    blocks = _collect_events(
        "rtu_event[]",
        max(64, len(data) // 8),
        lambda out, cap, n_out: lib.rtu_parse(
            parser,
            data,
            len(data),
            marks,
            n_marks[0],
            c_offsets,
            c_times,
            n_chunks,
            out,
            cap,
            n_out,
        ),
        "parse_stream: rtu_parse",
    )
    c = parser.counters
    counters = counters_dict(list(c.frames), list(c.discarded), int(c.discard_events))
    return CFrameList(data, blocks, counters)


def _timing(options: CoreOptions) -> Timing:
    cfg = _config(options)
    return Timing(int(cfg.timing.char_us), int(cfg.timing.t15_us), int(cfg.timing.t35_us))


Framer, parse_stream, char_timing = backend_framing(BACKEND, _Core, _parse, _timing)


# ---- Modbus TCP: MBAP framing (csrc/rtu_mbap.c) ----------------------------


class _MbapCore:
    def __init__(self, role: int) -> None:
        self.f = _initialised("rtu_mbap_framer *", lib.rtu_mbap_framer_init, role, f"role {role}")

    def feed(self, data: bytes) -> int:
        return int(lib.rtu_mbap_framer_feed(self.f, data, len(data)))

    def close(self) -> None:
        lib.rtu_mbap_framer_close(self.f)

    def poll(self) -> MbapEvent | None:
        f = self.f
        if not lib.rtu_mbap_framer_poll(f):
            return None
        e = f.event
        adu = ffi.unpack(ffi.cast("char *", lib.rtu_mbap_framer_event_data(f)), e.length)
        return (int(e.offset), int(e.length), int(e.kind), int(e.error), adu)

    def needed(self) -> int:
        return int(lib.rtu_mbap_framer_needed(self.f))

    def error(self) -> int:
        return int(self.f.error)

    def counts(self) -> tuple[Sequence[int], Sequence[int], int]:
        c = self.f.counters
        return list(c.frames), list(c.discarded), int(c.discard_events)


def _mbap_encode(transaction: int, unit: int, pdu: bytes) -> bytes:
    out = ffi.new("uint8_t[]", 7 + len(pdu))
    n = ffi.new("size_t *")
    status = lib.rtu_mbap_encode(transaction, unit, pdu, len(pdu), out, len(out), n)
    if status != lib.RTU_OK:
        raise ValueError(f"encode_mbap: rtu_mbap_encode failed with status {status}")
    return bytes(ffi.buffer(out, n[0]))


class CMbapFrameList(_CEntries, MbapFrameList):
    """Entries live in C arrays (blocks of rtu_mbap_event); frames are built on access."""

    def _entry(self, i: int) -> tuple[int, int, int, int]:
        e = self._entries[i]
        return int(e.offset), int(e.length), int(e.kind), int(e.error)


def _parse_tcp(role: int, data: bytes) -> CMbapFrameList:
    parser = _initialised("rtu_mbap_parser *", lib.rtu_mbap_parser_init, role, f"role {role}")
    blocks = _collect_events(
        "rtu_mbap_event[]",
        # An ADU is 8..260 bytes: len // 8 + 1 entries always suffice; start smaller.
        max(64, len(data) // 64),
        lambda out, cap, n_out: lib.rtu_mbap_parse(parser, data, len(data), out, cap, n_out),
        "parse_tcp_stream: rtu_mbap_parse",
    )
    c = parser.counters
    counters = mbap_counters_dict(list(c.frames), list(c.discarded), int(c.discard_events))
    return CMbapFrameList(data, blocks, counters)


MbapFramer, parse_tcp_stream, encode_mbap = backend_mbap(
    BACKEND, _MbapCore, _mbap_encode, _parse_tcp
)
