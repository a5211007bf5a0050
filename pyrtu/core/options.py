"""The framer core's options (`CoreOptions`): what the C core and its Python twin
are configured with, checked once for both backends.

Not a user-facing configuration: a serial line is described by `pyrtu.core.line.LineConfig`
(``LineConfig.options(role)`` makes these), and the poller's buses, devices and
points by `pyrtu.poller.config`.  `core_options` is the framer keywords' validator,
which `LineConfig` calls in its constructor so that both say the same words.
"""

from __future__ import annotations

from dataclasses import dataclass

from pyrtu.core._errtypes import ArgumentTypeError
from pyrtu.core.rules import RuleTable, check_rules
from pyrtu.core.timing import (
    TIMING_RULES,
    bits_per_char,
    check_baudrate,
    check_timing,
    seconds_to_us,
)

ROLES = {"master": 0, "slave": 1, "monitor": 2}
MAX_ADU_LIMIT = 1024
DEFAULT_FLUSH_US = 50_000


@dataclass(frozen=True)
class CoreOptions:
    """Validated framer options; the backends turn them into their own config."""

    role: int
    baudrate: int
    bits: int
    rule: int  # 0 modbus, 1 weg
    t15_us: int | None
    t35_us: int | None
    strict: bool
    max_adu: int
    flush_us: int | None
    rules: RuleTable


def core_options(
    role: str,
    *,
    baudrate: int = 19200,
    parity: str = "E",
    stopbits: float = 1,
    bytesize: int = 8,
    timing: str = "modbus",
    t15: float | None = None,
    t35: float | None = None,
    strict: bool = False,
    max_adu: int = 256,
    rules: RuleTable | None = None,
    flush_timeout: float | None = None,
) -> CoreOptions:
    if role not in ROLES:
        raise ValueError(f"role must be 'master', 'slave' or 'monitor', not {role!r}")
    check_baudrate(baudrate)
    check_timing(timing)
    if isinstance(max_adu, bool) or not isinstance(max_adu, int):
        raise ArgumentTypeError(f"max_adu must be 4..{MAX_ADU_LIMIT} bytes, not {max_adu!r}")
    if not 4 <= max_adu <= MAX_ADU_LIMIT:
        raise ValueError(f"max_adu must be 4..{MAX_ADU_LIMIT} bytes, not {max_adu!r}")
    return CoreOptions(
        role=ROLES[role],
        baudrate=baudrate,
        bits=bits_per_char(parity, stopbits, bytesize),
        rule=TIMING_RULES.index(timing),
        t15_us=None if t15 is None else seconds_to_us(t15, "t15"),
        t35_us=None if t35 is None else seconds_to_us(t35, "t35"),
        strict=bool(strict),
        max_adu=max_adu,
        flush_us=None if flush_timeout is None else seconds_to_us(flush_timeout, "flush_timeout"),
        rules=check_rules(rules),
    )


def flush_us_for(options: CoreOptions, t35_us: int) -> int:
    """Lenient mode drops incomplete bytes after this silence (never below t3.5)."""
    flush = DEFAULT_FLUSH_US if options.flush_us is None else options.flush_us
    return max(flush, t35_us)


def to_microseconds(now: float) -> int:
    """`now` (seconds, monotonic clock) as the C core's integer microseconds."""
    return round(now * 1_000_000)
