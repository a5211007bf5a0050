"""`LineConfig`: one validated description of a serial line, for every layer.

(`pyrtu.core.options` holds the framer core's internal options a LineConfig makes;
`pyrtu.poller.config` the poller's buses and points, each bus with its LineConfig.)
The public constructors that take the line keywords turn them into a LineConfig
with `line_from` (``line=`` or the keywords, not both; an unknown one is a
TypeError), whose defaults are `LINE_DEFAULTS` (the dataclass's own).

The framer, the client and server protocols, the sync and asyncio drivers, the
CLI and the virtual bus all take a `LineConfig` (the ten framer keywords were
written out in six places before it)::

    line = LineConfig(baudrate=9600, parity="N", stopbits=2)
    line.times            # Timing(char_us=1146, t15_us=1719, t35_us=4010)
    line.t35_time         # 0.00401 (seconds)
    framer = pyrtu.Framer("master", line=line)

Fields (all keyword, all checked in the constructor; a bad value raises
ValueError, or TypeError for a wrong type, naming the keyword).  This is the one
validator of line parameters: the framers, `pyrtu.Master`/`AsyncMaster`,
`Slave`/`AsyncSlave`, the virtual bus, the poller's TOML loader and the command
line all check through it (or through the same `pyrtu.core.timing` checks), so a bad
value gets the same words everywhere, e.g. ``baudrate must be an integer
50..4000000, not 1000000000``:

* ``baudrate`` (50..4000000: `pyrtu.core.timing.MIN_BAUDRATE`/`MAX_BAUDRATE`, the
  range termios names), ``parity`` ("N", "E", "O", "M", "S"), ``stopbits`` (1,
  1.5, 2), ``bytesize`` (7, 8): the byte format (Modbus over Serial Line V1.02,
  2.5.1).
* ``mode``: "rtu" or "ascii" (2.5.1 / 2.5.2).
* ``timing``: "modbus" (fixed 750 / 1750 us above 19200 baud, 2.5.1.1) or
  "weg" (the WEG manuals keep the 19200-baud values above 19200).
* ``t15``, ``t35``: overrides of t1.5 and t3.5 in seconds (0 turns the silence
  detection off, for links without wire timing).
* ``max_adu``: the longest RTU ADU accepted (4..1024; 256 per 2.5.1).
* ``strict``: a silence of t3.5 always ends a frame, and a t1.5 gap inside one
  discards it (default: lenient, for USB adapters that batch bytes).
* ``rules``: vendor length rules, ``{fc: (request_rule, response_rule)}``.
* ``flush_timeout``: lenient mode drops an incomplete frame after this silence
  (default 50 ms, never below t3.5).
* ``inter_char``: ASCII mode's longest silence inside a frame (1 s, 2.5.2.1).

The derived timing comes from the same integer arithmetic as the C core
(``rtu_timing_init``), with the overrides applied.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, TypedDict

from pyrtu.core._errtypes import ArgumentTypeError
from pyrtu.core.options import CoreOptions, core_options
from pyrtu.core.rules import RuleTable
from pyrtu.core.timing import (
    MAX_BAUDRATE,
    MIN_BAUDRATE,
    MODES,
    Timing,
    apply_overrides,
    check_baudrate,
    check_bytesize,
    check_mode,
    check_parity,
    check_stopbits,
    check_timing,
    compute_timing,
    positive_seconds,
)


def _optional_seconds(name: str, value: object) -> None:
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ArgumentTypeError(f"{name} must be a non-negative number of seconds, not {value!r}")
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a non-negative number of seconds, not {value!r}")


@dataclass(frozen=True)
class LineConfig:
    """The line: byte format, mode, timing rule and framing options (see module doc)."""

    baudrate: int = 19200
    parity: str = "E"
    stopbits: float = 1
    bytesize: int = 8
    mode: str = "rtu"
    timing: str = "modbus"
    t15: float | None = None
    t35: float | None = None
    max_adu: int = 256
    strict: bool = False
    rules: RuleTable = field(default_factory=dict, hash=False)
    flush_timeout: float | None = None
    inter_char: float = 1.0

    def __post_init__(self) -> None:
        check_baudrate(self.baudrate)
        parity = check_parity(self.parity)
        check_bytesize(self.bytesize)
        check_stopbits(self.stopbits)
        check_mode(self.mode)
        for name in ("t15", "t35", "flush_timeout"):
            _optional_seconds(name, getattr(self, name))
        positive_seconds(self.inter_char, "inter_char")
        if not isinstance(self.strict, bool):
            raise ArgumentTypeError(f"strict must be True or False, not {self.strict!r}")
        # The framer's checks, with the framer's messages (they name the keyword).
        options = core_options("master", **self._framer_kwargs(parity))
        object.__setattr__(self, "parity", parity)
        object.__setattr__(self, "rules", MappingProxyType(dict(options.rules)))
        object.__setattr__(self, "_bits", options.bits)
        base = compute_timing(self.baudrate, options.bits, self.timing)
        object.__setattr__(self, "_times", apply_overrides(base, self.t15, self.t35))

    def _framer_kwargs(self, parity: str | None = None) -> dict[str, Any]:
        kwargs = {name: getattr(self, name) for name in _FRAMER_KEYWORDS}
        if parity is not None:
            kwargs["parity"] = parity
        return kwargs

    # ------------------------------------------------------------ derived values

    @property
    def bits(self) -> int:
        """Bits per character: start + data + parity + stop (11 for 8E1)."""
        return int(self.__dict__["_bits"])

    @property
    def times(self) -> Timing:
        """Character time, t1.5 and t3.5 (integer microseconds; ``.char``, ``.t15``,
        ``.t35`` in seconds), overrides applied."""
        times: Timing = self.__dict__["_times"]
        return times

    @property
    def char_time(self) -> float:
        """One character on the wire, in seconds."""
        return self.times.char

    @property
    def t15_time(self) -> float:
        """The inter-character limit t1.5 in seconds (override applied)."""
        return self.times.t15

    @property
    def t35_time(self) -> float:
        """The inter-frame silence t3.5 in seconds (override applied)."""
        return self.times.t35

    @property
    def frame_gap(self) -> float:
        """The silence a sender keeps between frames: t3.5 in RTU, none in ASCII
        (frames are delimited by ':' and CR LF, 2.5.2.1)."""
        return self.times.t35 if self.mode == "rtu" else 0.0

    def wire_time(self, nbytes: int) -> float:
        """Seconds that ``nbytes`` characters take on the wire."""
        return nbytes * self.times.char

    # ------------------------------------------------------------ other shapes

    def options(self, role: str) -> CoreOptions:
        """The backends' internal options for a framer of ``role``."""
        return core_options(role, **self._framer_kwargs())

    def framer_kwargs(self) -> dict[str, Any]:
        """The framer keywords (``Framer(role, **line.framer_kwargs())``)."""
        return self._framer_kwargs()

    def replace(self, **changes: Any) -> LineConfig:
        """A copy with ``changes`` applied (checked like the constructor)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def of(cls, line: LineConfig | None = None, **kwargs: Any) -> LineConfig:
        """``line`` with ``kwargs`` applied, or a new LineConfig from ``kwargs``."""
        if line is None:
            return cls(**kwargs)
        if not isinstance(line, LineConfig):
            raise TypeError(f"line must be a LineConfig, not {type(line).__name__}")
        return line.replace(**kwargs) if kwargs else line


class ByteFormat(TypedDict, total=False):
    """The byte format of a serial port (`pyrtu.drivers.port.open_port`'s keywords)."""

    baudrate: int
    parity: str
    stopbits: float
    bytesize: int


#: the keywords of the byte format, in `ByteFormat`'s order
BYTE_FORMAT: tuple[str, ...] = tuple(ByteFormat.__annotations__)


class FormatKeywords(ByteFormat, total=False):
    """The line keywords of ``parse_stream`` (the fields of `LineConfig`; the
    constructors that take them as ``**keywords`` type them with these)."""

    timing: str
    t15: float | None
    t35: float | None
    strict: bool
    max_adu: int
    rules: RuleTable | None


class FramerKeywords(FormatKeywords, total=False):
    """The line keywords of `pyrtu.Framer`."""

    flush_timeout: float | None


#: the keywords of `FramerKeywords`, in its order (the fields of a `LineConfig` a framer takes)
_FRAMER_KEYWORDS: tuple[str, ...] = tuple(FramerKeywords.__annotations__)


class LineKeywords(FramerKeywords, total=False):
    """Every line keyword (`pyrtu.Slave`, `pyrtu.drivers.aio.AsyncSlave`)."""

    mode: str
    inter_char: float


#: The one table of the line keywords' defaults (the constructors that take the
#: keywords, `pyrtu.Master`, `pyrtu.Slave`, their asyncio twins, the framers and the
#: virtual bus, default to these; ``rules`` None is no vendor rules).
LINE_DEFAULTS: MappingProxyType[str, Any] = MappingProxyType(
    {
        f.name: (None if f.default is dataclasses.MISSING else f.default)
        for f in dataclasses.fields(LineConfig)
    }
)


def line_from(line: LineConfig | None, where: str = "", **keywords: Any) -> LineConfig:
    """The `LineConfig` of a constructor that takes ``line=`` or the line keywords:
    ``line`` as given, or a new one from ``keywords`` (those left at their defaults
    may be passed too).  TypeError when both are given, when ``line`` is not a
    LineConfig, or for a keyword that is not a line keyword (named)."""
    prefix = f"{where}: " if where else ""
    check_keywords(keywords, LINE_DEFAULTS, where or "line_from")
    if line is None:
        return LineConfig(**{k: v for k, v in keywords.items() if k != "rules" or v is not None})
    if not isinstance(line, LineConfig):
        raise TypeError(f"{prefix}line must be a LineConfig, not {type(line).__name__}")
    given = [k for k, v in keywords.items() if v != LINE_DEFAULTS[k] and not _same(v, k)]
    if given:
        raise TypeError(f"{prefix}give line= or the line keywords ({', '.join(given)}), not both")
    return line


def check_keywords(keywords: Mapping[str, object], known: Iterable[str], where: str) -> None:
    """TypeError, in Python's words, for a keyword of ``keywords`` not in ``known``
    (the line keywords of a constructor that takes them as ``**keywords``)."""
    allowed = set(known)
    for key in keywords:
        if key not in allowed:
            raise TypeError(f"{where}() got an unexpected keyword argument {key!r}")


def _same(value: object, key: str) -> bool:
    """Whether ``value`` is the default of ``key`` written another way (rules: {})."""
    return key == "rules" and value is None


def adopt_port_format(line: LineConfig, port: Any) -> LineConfig:
    """``line`` with the byte format of ``port`` (an open pyserial object passed in
    keeps its own format: the line follows it)."""
    fmt = {k: getattr(port, k) for k in BYTE_FORMAT}
    if all(getattr(line, k) == v for k, v in fmt.items()):
        return line
    return line.replace(**fmt)


def split_field_error(exc: BaseException, names: tuple[str, ...]) -> tuple[str | None, str]:
    """``("baudrate", "must be ...")`` from the validators' ``"baudrate must be ..."``
    (None and the whole message when it names none of ``names``): how the TOML loader
    and the command line put the same words after their own ``file:line: key:`` or
    ``argument --flag:``."""
    text = str(exc)
    for name in names:
        if text.startswith(name + " "):
            return name, text[len(name) + 1 :]
    return None, text


__all__ = [
    "LINE_DEFAULTS",
    "MAX_BAUDRATE",
    "MIN_BAUDRATE",
    "MODES",
    "FormatKeywords",
    "FramerKeywords",
    "LineConfig",
    "LineKeywords",
    "check_baudrate",
    "check_bytesize",
    "check_keywords",
    "check_mode",
    "check_parity",
    "check_stopbits",
    "check_timing",
    "line_from",
    "split_field_error",
]
