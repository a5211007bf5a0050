"""Small pieces shared by the device modules: word conversions and flag words."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Protocol

from pyrtu.core.rules import LengthRule


def _unsigned(value: int, bits: int) -> int:
    """A signed or unsigned ``bits``-wide value as two's complement (ValueError if wider)."""
    if not -(1 << (bits - 1)) <= value < 1 << bits:
        raise ValueError(f"{value} does not fit in {bits} bits")
    return value & ((1 << bits) - 1)


def _signed(value: int, bits: int) -> int:
    """The low ``bits`` of ``value`` read as a signed number."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def u16(value: int) -> int:
    """A signed or unsigned 16-bit value as it goes in a register (0..65535)."""
    return _unsigned(value, 16)


def s16(value: int) -> int:
    """A register value read as a signed 16-bit number."""
    return _signed(value, 16)


def u32(value: int) -> int:
    """A signed or unsigned 32-bit value as two's complement (0..2**32-1)."""
    return _unsigned(value, 32)


def s32(value: int) -> int:
    """A 32-bit field read as a signed number."""
    return _signed(value, 32)


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


def masked_word(obj: object, masks: Mapping[str, int]) -> int:
    """The OR of the ``masks`` (``{field: mask}``) whose boolean field of ``obj`` is set."""
    word = 0
    for name, mask in masks.items():
        if getattr(obj, name):
            word |= mask
    return word


def masked_flags(word: int, masks: Mapping[str, int]) -> dict[str, bool]:
    """``{field: bool}``: whether each mask of ``masks`` is set in ``word``."""
    return {name: bool(word & mask) for name, mask in masks.items()}


def flag(bit: int) -> Any:
    """A boolean field of a `FlagWord` that is bit ``bit`` of its word (default False):
    the field list is the word's one bit table (`FlagWord.flags_in`, `FlagWord.flag_bits`)."""
    return field(default=False, metadata={"bit": bit})


@dataclass(frozen=True)
class FlagWord:
    """Base for decoded status/control words: boolean fields plus the raw ``word``.

    `active` lists the fields that are set; ``str()`` joins them for people.  Fields
    declared with `flag` carry their bit: `flags_in` reads them from a word, `flag_bits`
    puts them back.
    """

    word: int

    @classmethod
    def flags_in(cls, word: int) -> dict[str, bool]:
        """``{field: bool}`` for the `flag` fields, from their bits in ``word``."""
        bits = {f.name: f.metadata["bit"] for f in fields(cls) if "bit" in f.metadata}
        return {name: bool(word >> bit & 1) for name, bit in bits.items()}

    def flag_bits(self) -> int:
        """The word with the bits of the `flag` fields that are set."""
        word = 0
        for f in fields(self):
            if "bit" in f.metadata and getattr(self, f.name):
                word |= 1 << f.metadata["bit"]
        return word

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
