"""Length rules for function codes, so frames end without waiting for silence.

The C core knows every public function code of the Modbus Application Protocol
V1.1b that runs on a serial line.  Vendor codes are registered at run time as a
rule per direction: a fixed ADU length, or a count field (libmodbus-style:
function -> meta -> data).  Lengths are whole ADUs: address + PDU + CRC.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from pyrtu.core._errtypes import ArgumentTypeError

RULE_NONE = 0
RULE_FIXED = 1
RULE_COUNT = 2


@dataclass(frozen=True, slots=True)
class LengthRule:
    """How long the ADU of one function code is, in one direction.

    ``LengthRule.fixed(n)``: always n bytes.  ``LengthRule.counted(offset, width,
    scale, tail)``: a big-endian count of ``width`` bytes at ``offset``; the ADU is
    ``offset + width + count * scale + tail`` bytes (tail = data after the counted
    part, CRC included).
    """

    type: int
    offset: int = 0
    width: int = 0
    scale: int = 1
    add: int = 0

    @classmethod
    def fixed(cls, length: int) -> LengthRule:
        if not isinstance(length, int) or not 4 <= length <= 1024:
            raise ValueError(f"a fixed ADU length must be 4..1024 bytes, not {length!r}")
        return cls(RULE_FIXED, add=length)

    @classmethod
    def counted(cls, offset: int, width: int = 1, scale: int = 1, tail: int = 2) -> LengthRule:
        if not isinstance(offset, int) or not 2 <= offset <= 250:
            raise ValueError(
                f"count offset must be 2..250 (after address and function), not {offset!r}"
            )
        if width not in (1, 2):
            raise ValueError(f"count width must be 1 or 2 bytes, not {width!r}")
        if not isinstance(scale, int) or not 1 <= scale <= 255:
            raise ValueError(f"count scale must be 1..255, not {scale!r}")
        if not isinstance(tail, int) or not 2 <= tail <= 1024:
            raise ValueError(f"tail must be 2..1024 bytes (it includes the CRC), not {tail!r}")
        return cls(RULE_COUNT, offset=offset, width=width, scale=scale, add=tail)

    def length(self, adu: bytes | bytearray | memoryview) -> int | None:
        """The ADU length this rule gives for the bytes so far, or None if more are needed."""
        if self.type == RULE_FIXED:
            return self.add
        meta = self.offset + self.width
        if len(adu) < meta:
            return None
        count = int.from_bytes(bytes(adu[self.offset : meta]), "big")
        return meta + count * self.scale + self.add


#: fc -> (request rule, response rule); None leaves that direction unknown.
RuleTable = Mapping[int, tuple[LengthRule | None, LengthRule | None]]


def check_rules(rules: RuleTable | None) -> dict[int, tuple[LengthRule | None, LengthRule | None]]:
    """Validate a rule table given by a user; raises ValueError naming the entry."""
    out: dict[int, tuple[LengthRule | None, LengthRule | None]] = {}
    for fc, pair in (rules or {}).items():
        if isinstance(fc, bool) or not isinstance(fc, int):
            raise ArgumentTypeError(f"rules: function code must be 1..127, not {fc!r}")
        if not 1 <= fc <= 127:
            raise ValueError(f"rules: function code must be 1..127, not {fc!r}")
        if not isinstance(pair, tuple):
            raise ArgumentTypeError(
                f"rules[{fc}]: give (request_rule, response_rule), not {pair!r}"
            )
        if len(pair) != 2:
            raise ValueError(f"rules[{fc}]: give (request_rule, response_rule), not {pair!r}")
        for rule in pair:
            if rule is not None and not isinstance(rule, LengthRule):
                raise ArgumentTypeError(f"rules[{fc}]: {rule!r} is not a LengthRule")
        out[fc] = pair
    return out


#: Bonfiglioli Vectron ACT/ACU (seed 004, 6.4.3 and 6.4.4): FC 100 reads a 32-bit
#: parameter (request: address, 0x64, 2-byte data set/parameter, CRC; response:
#: address, 0x64, 4-byte value, CRC); FC 101 writes one and echoes it.
BONFIGLIOLI: RuleTable = {
    100: (LengthRule.fixed(6), LengthRule.fixed(8)),
    101: (LengthRule.fixed(10), LengthRule.fixed(10)),
}

#: CV100/FV100 (seed 003, section 5): 0x41 writes one register and keeps it after
#: power-off (frame as FC 06), 0x43 writes several and keeps them (frame as FC 16).
#: 0x42 ("manage function code") has no frame layout in the manual; it is framed
#: like FC 08 (2-byte sub-function + 2-byte data) and otherwise by silence.
CV100: RuleTable = {
    0x41: (LengthRule.fixed(8), LengthRule.fixed(8)),
    0x42: (LengthRule.fixed(8), LengthRule.fixed(8)),
    0x43: (LengthRule.counted(6), LengthRule.fixed(8)),
}
