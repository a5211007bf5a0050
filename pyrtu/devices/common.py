"""Small pieces shared by the device modules: word conversions and flag words."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Protocol

from ..rules import LengthRule


def u16(value: int) -> int:
    """A signed or unsigned 16-bit value as it goes in a register (0..65535)."""
    if not -0x8000 <= value <= 0xFFFF:
        raise ValueError(f"{value} does not fit in 16 bits")
    return value & 0xFFFF


def s16(value: int) -> int:
    """A register value read as a signed 16-bit number."""
    value &= 0xFFFF
    return value - 0x10000 if value & 0x8000 else value


def u32(value: int) -> int:
    """A signed or unsigned 32-bit value as two's complement (0..2**32-1)."""
    if not -0x8000_0000 <= value <= 0xFFFF_FFFF:
        raise ValueError(f"{value} does not fit in 32 bits")
    return value & 0xFFFF_FFFF


def s32(value: int) -> int:
    """A 32-bit field read as a signed number."""
    value &= 0xFFFF_FFFF
    return value - 0x1_0000_0000 if value & 0x8000_0000 else value


def scaled(raw: int, decimals: int) -> float:
    """A value transmitted without its decimal point, as a number (``103, 1 -> 10.3``)."""
    return raw / 10**decimals if decimals else float(raw)


def unscaled(value: float, decimals: int) -> int:
    """A number as transmitted without its decimal point (``10.3, 1 -> 103``)."""
    return round(value * float(10**decimals))


def bits_of(word: int, layout: Mapping[int, str]) -> dict[str, bool]:
    """``{name: bool}`` for the named bits of ``word``."""
    return {name: bool(word >> bit & 1) for bit, name in layout.items()}


def word_of(flags: Mapping[str, bool], layout: Mapping[int, str]) -> int:
    """The word with the named bits of ``flags`` set (unknown names: ValueError)."""
    by_name = {name: bit for bit, name in layout.items()}
    word = 0
    for name, on in flags.items():
        if name not in by_name:
            raise ValueError(f"no bit named {name!r}; known: {', '.join(sorted(by_name))}")
        if on:
            word |= 1 << by_name[name]
    return word


@dataclass(frozen=True)
class FlagWord:
    """Base for decoded status/control words: boolean fields plus the raw ``word``.

    `active` lists the fields that are set; ``str()`` joins them for people.
    """

    word: int

    def active(self) -> list[str]:
        return [f.name for f in fields(self) if f.name != "word" and getattr(self, f.name) is True]

    def __str__(self) -> str:
        return ", ".join(self.active()) or "none"


def join(words: Iterable[str]) -> str:
    """Comma-joined words, or ``"-"`` when there are none."""
    out = ", ".join(w for w in words if w)
    return out or "-"


class MasterLike(Protocol):
    """The part of `pyrtu.Master` the profiles use (any object with these methods)."""

    def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]: ...

    def write_register(self, slave: int, address: int, value: int) -> None: ...

    def write_registers(self, slave: int, address: int, values: Sequence[int]) -> None: ...

    def read_device_identification(
        self, slave: int, read_code: int = 1, object_id: int = 0
    ) -> dict[int, bytes]: ...

    def diagnostics(self, slave: int, sub_function: int, data: int = 0) -> int: ...

    def execute(
        self,
        slave: int,
        function: int,
        data: bytes,
        *,
        request_rule: LengthRule | None = None,
        response_rule: LengthRule | None = None,
    ) -> bytes: ...
