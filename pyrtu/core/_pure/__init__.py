"""The pure-Python backend: the same names and behaviour as the C core."""

from __future__ import annotations

from array import array
from collections.abc import Callable, Sequence

from pyrtu.core._pure import mbap as _mbap_core
from pyrtu.core._pure.crc import (  # noqa: F401 (the crc names of BACKEND_NAMES)
    add_crc,
    check_crc,
    crc16,
    crc16_path,
    crc16_paths,
    lrc,
)
from pyrtu.core._pure.framer import CoreFramer
from pyrtu.core._pure.head import Config
from pyrtu.core._pure.predict import DIR_REQUEST, make_rules, predict
from pyrtu.core._pure.stream import CoreParser, Entry
from pyrtu.core._types import BACKEND_NAMES
from pyrtu.core.frames import FrameList
from pyrtu.core.framing import backend_framing, check_core_limits, counters_dict
from pyrtu.core.mbap import MbapEvent, MbapFrameList, backend_mbap, mbap_counters_dict
from pyrtu.core.options import CoreOptions, flush_us_for
from pyrtu.core.timing import Timing, compute_timing

BACKEND = "python"

__all__ = list(BACKEND_NAMES)


def _config(options: CoreOptions) -> Config:
    check_core_limits(options)
    base = compute_timing(options.baudrate, options.bits, ("modbus", "weg")[options.rule])
    t15 = base.t15_us if options.t15_us is None else options.t15_us
    t35 = base.t35_us if options.t35_us is None else options.t35_us
    return Config(
        role=options.role,
        strict=options.strict,
        max_adu=options.max_adu,
        char_us=base.char_us,
        t15_us=t15,
        t35_us=t35,
        flush_us=flush_us_for(options, t35),
        rules=make_rules(options.rules),
    )


def request_predictor(options: CoreOptions) -> Callable[[bytes], tuple[int, int]]:
    """The request-length predictor of ``options``' rules (the twin of the C core's
    ``rtu_predict``): (PRED_*, length) for the bytes of a request so far."""
    rules = make_rules(options.rules)

    def request_length(adu: bytes) -> tuple[int, int]:
        return predict(rules, DIR_REQUEST, adu, len(adu))

    return request_length


class _Core(CoreFramer):
    """The twin's framer with the rest of the core interface: feed, poll, sent,
    reset, handle_timer, deadline and needed are `CoreFramer`'s own."""

    def __init__(self, options: CoreOptions) -> None:
        super().__init__(_config(options))

    def take(self) -> tuple[int, int, bytes] | None:
        ev = self.poll()
        return None if ev is None else (ev[3], ev[5], ev[6])

    def expect(self, adu: bytes) -> None:
        self.reset()
        self.sent(adu)

    def counts(self) -> tuple[Sequence[int], Sequence[int], int]:
        return self.frames, self.discarded, self.discard_events


class PyFrameList(FrameList):
    def __init__(self, data: bytes, entries: list[Entry], counters: dict[str, int]) -> None:
        super().__init__(data, len(entries))
        self._entries = entries
        self.counters = counters

    def _entry(self, i: int) -> Entry:
        return self._entries[i]


def _parse(
    options: CoreOptions, data: bytes, offsets: list[int], times_us: list[int]
) -> PyFrameList:
    parser = CoreParser(_config(options))
    entries = parser.parse(data, offsets, times_us)
    counters = counters_dict(parser.frames, parser.discarded, parser.discard_events)
    return PyFrameList(data, entries, counters)


def _timing(options: CoreOptions) -> Timing:
    cfg = _config(options)
    return Timing(cfg.char_us, cfg.t15_us, cfg.t35_us)


Framer, parse_stream, char_timing = backend_framing(BACKEND, _Core, _parse, _timing)


# ---- Modbus TCP: MBAP framing (the twin of csrc/rtu_mbap.c) -----------------


class _MbapCore:
    def __init__(self, role: int) -> None:
        self.f = _mbap_core.CoreMbapFramer(role)

    def feed(self, data: bytes) -> int:
        return self.f.feed(data)

    def close(self) -> None:
        self.f.close()

    def poll(self) -> MbapEvent | None:
        return self.f.poll()

    def needed(self) -> int:
        return self.f.needed()

    def error(self) -> int:
        return self.f.error

    def counts(self) -> tuple[Sequence[int], Sequence[int], int]:
        return self.f.frames, self.f.discarded, self.f.discard_events


class PyMbapFrameList(MbapFrameList):
    def __init__(
        self,
        data: bytes,
        entries: tuple[array[int], array[int], array[int], array[int]],
        counters: dict[str, int],
    ) -> None:
        super().__init__(data, len(entries[0]))
        self._offsets, self._lengths, self._kinds, self._errors = entries
        self.counters = counters

    def _entry(self, i: int) -> tuple[int, int, int, int]:
        return self._offsets[i], self._lengths[i], self._kinds[i], self._errors[i]


def _parse_tcp(role: int, data: bytes) -> PyMbapFrameList:
    parser = _mbap_core.CoreMbapParser(role)
    entries = parser.parse(data)
    counters = mbap_counters_dict(parser.frames, parser.discarded, parser.discard_events)
    return PyMbapFrameList(data, entries, counters)


MbapFramer, parse_tcp_stream, encode_mbap = backend_mbap(
    BACKEND, _MbapCore, _mbap_core.encode, _parse_tcp
)
