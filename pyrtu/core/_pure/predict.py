"""Frame-length prediction: the twin of csrc/rtu_predict.c (see its comments).

Steps as in libmodbus: function -> meta -> data.  Lengths are whole ADUs.
"""

from __future__ import annotations

from pyrtu.core.framing import PRED_LENGTH, PRED_NEED, PRED_UNKNOWN
from pyrtu.core.options import MAX_ADU_LIMIT
from pyrtu.core.rules import RULE_COUNT, RULE_FIXED, RULE_NONE, RuleTable

RULE_MEI = 3
DIR_REQUEST = 0
DIR_RESPONSE = 1

# (type, offset, width, scale, add)
Rule = tuple[int, int, int, int, int]
_NONE: Rule = (RULE_NONE, 0, 0, 0, 0)


def _fixed(n: int) -> Rule:
    return (RULE_FIXED, 0, 0, 0, n)


def _count(off: int, width: int, add: int) -> Rule:
    return (RULE_COUNT, off, width, 1, add)


def make_rules(extra: RuleTable) -> tuple[list[Rule], list[Rule]]:
    """Standard rules (Application Protocol V1.1b section 6) plus user rules."""
    q = [_NONE] * 256
    s = [_NONE] * 256
    for fc in (1, 2, 3, 4):
        q[fc] = _fixed(8)
        s[fc] = _count(2, 1, 2)
    q[5] = q[6] = s[5] = s[6] = _fixed(8)
    q[7], s[7] = _fixed(4), _fixed(5)
    q[8] = s[8] = _fixed(8)
    q[11], s[11] = _fixed(4), _fixed(8)
    q[12], s[12] = _fixed(4), _count(2, 1, 2)
    q[15] = q[16] = _count(6, 1, 2)
    s[15] = s[16] = _fixed(8)
    q[17], s[17] = _fixed(4), _count(2, 1, 2)
    q[20] = q[21] = s[20] = s[21] = _count(2, 1, 2)
    q[22] = s[22] = _fixed(10)
    q[23], s[23] = _count(10, 1, 2), _count(2, 1, 2)
    q[24], s[24] = _fixed(6), _count(2, 2, 2)
    q[43] = s[43] = (RULE_MEI, 0, 0, 0, 0)
    for fc, (req, resp) in extra.items():
        for table, rule in ((q, req), (s, resp)):
            if rule is not None:
                table[fc] = (rule.type, rule.offset, rule.width, rule.scale, rule.add)
    return q, s


def _predict_mei_response(adu: bytes, n: int) -> tuple[int, int]:
    """Read Device Identification response (AP 6.21): walk the objects."""
    if n < 3:
        return PRED_NEED, 3
    if adu[2] != 0x0E:
        return PRED_UNKNOWN, 0
    if n < 8:
        return PRED_NEED, 8
    pos = 8
    for _ in range(adu[7]):
        if n < pos + 2:
            return PRED_NEED, pos + 2
        pos += 2 + adu[pos + 1]
        if pos > MAX_ADU_LIMIT:
            break
    return PRED_LENGTH, pos + 2


def predict(
    rules: tuple[list[Rule], list[Rule]], direction: int, adu: bytes, n: int
) -> tuple[int, int]:
    """(PRED_*, length) for the first n bytes of adu."""
    if n < 2:
        return PRED_NEED, 2
    fc = adu[1]
    if fc & 0x80:
        if direction != DIR_RESPONSE:
            return PRED_UNKNOWN, 0
        return PRED_LENGTH, 5
    rtype, off, width, mul, add = rules[direction][fc]
    if rtype == RULE_FIXED:
        return PRED_LENGTH, add
    if rtype == RULE_COUNT:
        meta = off + width
        if n < meta:
            return PRED_NEED, meta
        count = adu[off] if width == 1 else adu[off] << 8 | adu[off + 1]
        return PRED_LENGTH, meta + count * mul + add
    if rtype == RULE_MEI:
        if direction == DIR_RESPONSE:
            return _predict_mei_response(adu, n)
        if n < 3:
            return PRED_NEED, 3
        if adu[2] != 0x0E:
            return PRED_UNKNOWN, 0
        return PRED_LENGTH, 7
    return PRED_UNKNOWN, 0
