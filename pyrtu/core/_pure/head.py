"""Resolving the head of the unresolved bytes: the twin of csrc/rtu_head.c.

Candidates in order: predicted lengths (expected direction first), then the
silence-delimited lengths (Modbus over Serial Line 2.5.1.1).  The first whose
CRC checks is the frame; if none, wait when one may still complete, else
discard one byte so the caller slides to the next frame start.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from pyrtu.core._pure.crc import crc16
from pyrtu.core._pure.predict import DIR_REQUEST, DIR_RESPONSE, Rule, predict
from pyrtu.core.framing import PRED_NEED, PRED_UNKNOWN
from pyrtu.core.rules import RULE_COUNT, RULE_NONE

KIND_REQUEST, KIND_RESPONSE, KIND_EXCEPTION, KIND_UNKNOWN, KIND_DISCARD = range(5)
ERR_NONE, ERR_CRC, ERR_T15, ERR_OVERFLOW, ERR_UNKNOWN_FUNCTION, ERR_TRUNCATED = range(6)
ROLE_MASTER, ROLE_SLAVE, ROLE_MONITOR = range(3)
MARK_T15, MARK_T35 = 1, 2
ACT_WAIT, ACT_FRAME, ACT_DISCARD = range(3)

NOTE_CRC, NOTE_T15, NOTE_OVERFLOW, NOTE_TRUNCATED, NOTE_UNKNOWN = 1, 2, 4, 8, 16

# Time arithmetic of csrc/rtu_internal.h: int64 microseconds that saturate to
# [-INT64_MAX, INT64_MAX] after every step, in the C order, so that extreme times
# give the same results on both backends (INT64_MIN is the C core's "no time").
INT64_MAX = 2**63 - 1
TIME_MIN = -INT64_MAX


def time_clamp(a: int) -> int:
    return TIME_MIN if a < TIME_MIN else a


def sat_add(a: int, b: int) -> int:
    s = a + b
    return INT64_MAX if s > INT64_MAX else TIME_MIN if s < TIME_MIN else s


def sat_sub(a: int, b: int) -> int:
    return sat_add(a, -b)


def sat_mul(k: int, c: int) -> int:
    """k * c for k >= 0, clamped to INT64_MAX (0 for c <= 0)."""
    if c <= 0:
        return 0
    p = k * c
    return INT64_MAX if p > INT64_MAX else p


@dataclass
class Config:
    role: int
    strict: bool
    max_adu: int
    char_us: int
    t15_us: int
    t35_us: int
    flush_us: int
    rules: tuple[list[Rule], list[Rule]]


@dataclass
class Context:
    pending: bool = False
    address: int = 0
    function: int = 0

    def matches(self, adu: bytes) -> bool:
        return self.pending and adu[0] == self.address and (adu[1] & 0x7F) == self.function

    def update(self, kind: int, adu: bytes) -> None:
        if kind == KIND_REQUEST and adu[0] != 0:
            self.pending, self.address, self.function = True, adu[0], adu[1]
        else:
            self.pending = False


class CoreState:
    """What the framer and the parser both keep: the configuration, the request
    context and the counters of rtu_counters (frames by kind, discarded bytes by
    error, discard runs)."""

    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.ctx = Context()
        self.frames = [0, 0, 0, 0]
        self.discarded = [0] * 6
        self.discard_events = 0


@dataclass
class View:
    data: bytes  # the window, starting at the head byte
    base: int  # stream position of data[0]
    marks: list[tuple[int, int]]  # (pos, flags), ascending
    mi: int  # first mark with pos > base
    silent_end: bool
    closed: bool
    timed: bool


def _crc_ok(adu: bytes, length: int) -> bool:
    crc = crc16(adu[: length - 2])
    return adu[length - 2] == crc & 0xFF and adu[length - 1] == crc >> 8


def _has_gap(v: View, length: int) -> bool:
    for pos, flags in v.marks[v.mi :]:
        rel = pos - v.base
        if rel >= length:
            break
        if rel > 0 and flags & MARK_T15:
            return True
    return False


def _silence_kind(cfg: Config, ctx: Context, adu: bytes) -> int:
    if adu[1] & 0x80:
        return KIND_EXCEPTION
    if cfg.role == ROLE_MASTER or ctx.matches(adu):
        return KIND_RESPONSE
    if cfg.role == ROLE_SLAVE or cfg.rules[DIR_REQUEST][adu[1]][0] != RULE_NONE:
        return KIND_REQUEST
    return KIND_UNKNOWN


def _pick_error(notes: int) -> int:
    for note, err in (
        (NOTE_T15, ERR_T15),
        (NOTE_OVERFLOW, ERR_OVERFLOW),
        (NOTE_CRC, ERR_CRC),
        (NOTE_TRUNCATED, ERR_TRUNCATED),
        (NOTE_UNKNOWN, ERR_UNKNOWN_FUNCTION),
    ):
        if notes & note:
            return err
    return ERR_TRUNCATED


def _check(cfg: Config, v: View, length: int) -> int:
    """0 when data[:length] is a frame, else the NOTE_* that rules it out."""
    if length < 4:
        return NOTE_TRUNCATED
    if not _crc_ok(v.data, length):
        return NOTE_CRC
    if cfg.strict and _has_gap(v, length):
        return NOTE_T15
    return 0


def _later_heads(v: View, n: int) -> Iterator[tuple[int, View]]:
    """``(rel, view)`` for each t3.5 boundary inside the first ``n`` bytes of ``v``
    (not at its start), in order: where a later frame could begin."""
    for i in range(v.mi, len(v.marks)):
        pos, flags = v.marks[i]
        rel = pos - v.base
        if rel >= n:
            break
        if rel == 0 or not flags & MARK_T35:
            continue
        yield rel, View(v.data[rel:], pos, v.marks, i + 1, v.silent_end, v.closed, v.timed)


def try_head(cfg: Config, ctx: Context, v: View, allow_skip: bool) -> tuple[int, int, int]:
    """(ACT_*, length, kind-or-error)."""
    d = v.data
    n = len(d)
    pnotes = [0, 0]  # why each predicted candidate failed
    notes = 0  # why the silence-delimited candidates failed
    can_wait = False
    if n < 2:
        return (ACT_DISCARD, 1, ERR_TRUNCATED) if v.closed else (ACT_WAIT, 0, 0)

    if d[1] & 0x80 or cfg.role == ROLE_MASTER:
        kinds: tuple[int, ...] = (KIND_RESPONSE,)
    elif ctx.matches(d):
        kinds = (KIND_RESPONSE, KIND_REQUEST)
    else:
        kinds = (KIND_REQUEST, KIND_RESPONSE)
    for k, kind in enumerate(kinds):
        direction = DIR_REQUEST if kind == KIND_REQUEST else DIR_RESPONSE
        status, length = predict(cfg.rules, direction, d, n)
        if status == PRED_UNKNOWN:
            pnotes[k] = NOTE_UNKNOWN
            continue
        if length > cfg.max_adu:
            pnotes[k] = NOTE_OVERFLOW
            continue
        if status == PRED_NEED or length > n:
            can_wait = True
            pnotes[k] = NOTE_TRUNCATED
            continue
        note = _check(cfg, v, length)
        if not note:
            return ACT_FRAME, length, KIND_EXCEPTION if d[1] & 0x80 else kind
        pnotes[k] = note

    # Silence-delimited lengths: each t3.5 boundary (strict: the first), then the end;
    # none in lenient mode while a predicted length may still come and the silence
    # does not close the frame (a CRC that checks on a prefix must not cut it).
    boundaries = []
    if not (can_wait and not cfg.strict and not v.closed):
        boundaries = [
            pos - v.base
            for pos, flags in v.marks[v.mi :]
            if flags & MARK_T35 and 0 < pos - v.base < n
        ]
        if v.silent_end:
            boundaries.append(n)
    for p in boundaries:
        note = _check(cfg, v, p)
        if not note:
            return ACT_FRAME, p, _silence_kind(cfg, ctx, d)
        notes |= note
        if cfg.strict:
            break

    if not v.closed and (can_wait or (v.timed and not v.silent_end and n <= cfg.max_adu)):
        if allow_skip:
            for rel, sub in _later_heads(v, n):
                if try_head(cfg, ctx, sub, False)[0] == ACT_FRAME:
                    return ACT_DISCARD, rel, ERR_TRUNCATED
        return ACT_WAIT, 0, 0
    # The predicted candidates give the reason; the silence's only without them.
    return ACT_DISCARD, 1, _pick_error((pnotes[0] | pnotes[1]) or notes)


# ---- Bytes still needed: the lower bound a driver may sleep on (rtu_head.c) ----


def _min_length(rules: tuple[list[Rule], list[Rule]], direction: int, d: bytes, n: int) -> int:
    """The shortest frame of ``direction`` that starts with d[:n] (n >= 2); 0: no rule."""
    status, length = predict(rules, direction, d, n)
    if status == PRED_UNKNOWN:
        return 0
    if status == PRED_NEED:
        rule = rules[direction][d[1]]
        return length + rule[4] if rule[0] == RULE_COUNT else length + 2
    return length


def answer_min(rules: tuple[list[Rule], list[Rule]], address: int, function: int) -> int:
    """The shortest answer to (address, function): see rtu_answer_min."""
    length = _min_length(rules, DIR_RESPONSE, bytes((address, function & 0x7F)), 2)
    if length == 0:
        return 4
    return min(length, 5)


def head_needed(cfg: Config, ctx: Context, v: View) -> int:
    """Bytes that must still arrive before the head can end by its predicted length."""
    d = v.data
    n = len(d)
    least = 0
    if n < 2:
        if cfg.role == ROLE_MASTER and ctx.pending and (n == 0 or d[0] == ctx.address):
            least = answer_min(cfg.rules, ctx.address, ctx.function)
        elif n == 1:
            least = 2
    else:
        if d[1] & 0x80 or cfg.role == ROLE_MASTER:
            dirs: tuple[int, ...] = (DIR_RESPONSE,)
        else:
            dirs = (DIR_REQUEST, DIR_RESPONSE)
        for direction in dirs:
            length = _min_length(cfg.rules, direction, d, n)
            if n < length <= cfg.max_adu and (least == 0 or length < least):
                least = length
    need = least - n if least > n else 0
    for _, sub in _later_heads(v, n):
        s = head_needed(cfg, ctx, sub)
        if s and (need == 0 or s < need):
            need = s
        break
    return need
