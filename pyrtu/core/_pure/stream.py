"""The bulk stream parser in pure Python: the twin of csrc/rtu_stream.c."""

from __future__ import annotations

from pyrtu.core._pure.head import (
    ACT_DISCARD,
    KIND_DISCARD,
    MARK_T15,
    MARK_T35,
    Config,
    CoreState,
    View,
    sat_mul,
    sat_sub,
    time_clamp,
    try_head,
)

# (offset, length, kind, error, start_us or None, end_us or None)
Entry = tuple[int, int, int, int, int | None, int | None]


def _byte_time(char_us: int, times: list[int], c: int, end: int, i: int) -> int:
    at = sat_sub(time_clamp(times[c]), sat_mul(end - 1 - i, char_us))
    if c > 0 and at < time_clamp(times[c - 1]):
        at = time_clamp(times[c - 1])
    return at


def marks_from_chunks(
    cfg: Config, offsets: list[int], times: list[int], total: int
) -> list[tuple[int, int]]:
    if offsets and offsets[0] != 0:
        raise ValueError("chunks: the first chunk must start at offset 0")
    marks: list[tuple[int, int]] = []
    for c in range(len(offsets)):
        end = offsets[c + 1] if c + 1 < len(offsets) else total
        if end < offsets[c] or end > total:
            raise ValueError(
                f"chunks: offsets must be ascending and within the data (chunk {c} at {offsets[c]})"
            )
        if c == 0 or end == offsets[c]:
            continue
        first = _byte_time(cfg.char_us, times, c, end, offsets[c])
        silence = sat_sub(sat_sub(first, cfg.char_us), time_clamp(times[c - 1]))
        if cfg.t35_us > 0 and silence >= cfg.t35_us:
            marks.append((offsets[c], MARK_T15 | MARK_T35))
        elif cfg.t15_us > 0 and silence > cfg.t15_us:
            marks.append((offsets[c], MARK_T15))
    return marks


class CoreParser(CoreState):
    def __init__(self, cfg: Config) -> None:
        super().__init__(cfg)

    def parse(self, data: bytes, offsets: list[int], times: list[int]) -> list[Entry]:
        cfg = self.cfg
        marks = marks_from_chunks(cfg, offsets, times, len(data)) if offsets else []
        timed = bool(offsets)
        total = len(data)
        out: list[Entry] = []
        chunk = [0]

        def byte_time(i: int) -> int | None:
            if not timed:
                return None
            c = chunk[0]
            while c + 1 < len(offsets) and offsets[c + 1] <= i:
                c += 1
            while c > 0 and offsets[c] > i:
                c -= 1
            chunk[0] = c
            end = offsets[c + 1] if c + 1 < len(offsets) else total
            return _byte_time(cfg.char_us, times, c, end, i)

        def entry(at: int, length: int, kind: int, error: int) -> Entry:
            first = byte_time(at)
            return (
                at,
                length,
                kind,
                error,
                None if first is None else sat_sub(first, cfg.char_us),
                byte_time(at + length - 1),
            )

        pos = 0
        mi = 0
        run = 0
        run_error = 0
        run_start = 0
        while pos < total:
            while mi < len(marks) and marks[mi][0] <= pos:
                mi += 1
            limit = total - pos
            if cfg.strict:
                for m in range(mi, len(marks)):
                    if marks[m][1] & MARK_T35:
                        limit = min(limit, marks[m][0] - pos)
                        break
            window = min(limit, cfg.max_adu)
            silent_end = window == limit
            for mpos, mflags in marks[mi:]:
                if silent_end or mpos - pos > window:
                    break
                if mpos - pos == window and mflags & MARK_T35:
                    silent_end = True
            v = View(data[pos : pos + window], pos, marks, mi, silent_end, True, timed)
            action, length, code = try_head(cfg, self.ctx, v, False)
            if action == ACT_DISCARD:
                if run == 0:
                    run_error, run_start = code, pos
                run += length
                pos += length
                self.discarded[run_error] += length
                continue
            if run:
                out.append(entry(run_start, run, KIND_DISCARD, run_error))
                self.discard_events += 1
                run = 0
            out.append(entry(pos, length, code, 0))
            self.ctx.update(code, v.data)
            self.frames[code] += 1
            pos += length
        if run:
            out.append(entry(run_start, run, KIND_DISCARD, run_error))
            self.discard_events += 1
        return out
