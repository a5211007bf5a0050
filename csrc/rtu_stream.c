/* The bulk stream parser: one call resolves a whole buffer (a capture) into
 * frames and discard runs, with the same head step as the framer.  Arrival
 * times are optional: chunks (offset, time) give them, one chunk per byte for
 * per-byte times; without them only prediction and CRC split the stream.
 * Chunk times may be any int64 (RTU_NO_TIME reads as the earliest time) and
 * need not ascend: the time arithmetic saturates (rtu_internal.h). */
#include "rtu_internal.h"

#include <string.h>

static int64_t rtu_chunk_prev(const int64_t *times, size_t c)
{
    return c > 0 ? rtu_time_clamp(times[c - 1]) : RTU_NO_TIME;
}

/* Arrival of byte i of chunk c (chunk ends at `end`): spread back over the
 * character time from the chunk's time, never before the previous chunk. */
static int64_t rtu_byte_time(const rtu_timing *t, const int64_t *times, size_t c, uint64_t end,
                             uint64_t i)
{
    int64_t at = rtu_sat_sub(rtu_time_clamp(times[c]), rtu_sat_mul(end - 1 - i, t->char_us));
    const int64_t prev = rtu_chunk_prev(times, c);
    if (prev != RTU_NO_TIME && at < prev) {
        at = prev;
    }
    return at;
}

int rtu_marks_from_chunks(const rtu_timing *t, const uint64_t *offsets, const int64_t *times,
                          size_t nchunks, uint64_t total, rtu_mark *out, size_t *nout)
{
    if (t == NULL || out == NULL || nout == NULL || (nchunks > 0 && (!offsets || !times)) ||
        t->char_us <= 0) {
        return RTU_EINVAL;
    }
    *nout = 0;
    if (nchunks > 0 && offsets[0] != 0) {
        return RTU_EINVAL;
    }
    for (size_t c = 0; c < nchunks; c++) {
        const uint64_t end = c + 1 < nchunks ? offsets[c + 1] : total;
        if (end < offsets[c] || end > total) {
            return RTU_EINVAL;
        }
        if (c == 0 || end == offsets[c]) {
            continue;
        }
        const int64_t first = rtu_byte_time(t, times, c, end, offsets[c]);
        const int64_t silence =
            rtu_sat_sub(rtu_sat_sub(first, t->char_us), rtu_time_clamp(times[c - 1]));
        uint32_t flags = 0;
        if (t->t35_us > 0 && silence >= t->t35_us) {
            flags = RTU_MARK_T15 | RTU_MARK_T35;
        } else if (t->t15_us > 0 && silence > t->t15_us) {
            flags = RTU_MARK_T15;
        }
        if (flags) {
            out[*nout].pos = offsets[c];
            out[*nout].flags = flags;
            out[*nout].reserved = 0;
            (*nout)++;
        }
    }
    return RTU_OK;
}

int rtu_parser_init(rtu_parser *p, const rtu_config *cfg)
{
    if (p == NULL || cfg == NULL || !rtu_config_valid(cfg)) {
        return RTU_EINVAL;
    }
    memset(p, 0, sizeof *p);
    p->cfg = cfg;
    return RTU_OK;
}

typedef struct {
    const uint64_t *offsets;
    const int64_t *times;
    size_t nchunks;
    uint64_t total;
} rtu_chunks;

static int64_t rtu_parser_time(rtu_parser *p, const rtu_chunks *ch, uint64_t i)
{
    if (ch->nchunks == 0) {
        return RTU_NO_TIME;
    }
    size_t c = p->chunk_index;
    while (c + 1 < ch->nchunks && ch->offsets[c + 1] <= i) {
        c++;
    }
    while (c > 0 && ch->offsets[c] > i) {
        c--;
    }
    p->chunk_index = c;
    const uint64_t end = c + 1 < ch->nchunks ? ch->offsets[c + 1] : ch->total;
    return rtu_byte_time(&p->cfg->timing, ch->times, c, end, i);
}

static void rtu_parser_event(rtu_parser *p, const rtu_chunks *ch, rtu_event *e, uint64_t at,
                             size_t len, int kind, int error)
{
    e->offset = at;
    e->length = (uint32_t)len;
    e->kind = (uint8_t)kind;
    e->error = (uint8_t)error;
    e->reserved = 0;
    const int64_t first = rtu_parser_time(p, ch, at);
    e->start_us = first == RTU_NO_TIME ? RTU_NO_TIME : rtu_sat_sub(first, p->cfg->timing.char_us);
    e->end_us = rtu_parser_time(p, ch, at + len - 1);
}

int rtu_parse(rtu_parser *p, const uint8_t *data, size_t len, const rtu_mark *marks, size_t nmarks,
              const uint64_t *offsets, const int64_t *times, size_t nchunks, rtu_event *out,
              size_t cap, size_t *nout)
{
    if (p == NULL || nout == NULL || (len > 0 && data == NULL) || (nmarks > 0 && marks == NULL) ||
        (nchunks > 0 && (offsets == NULL || times == NULL)) || (cap > 0 && out == NULL)) {
        return RTU_EINVAL;
    }
    *nout = 0;
    if (cap == 0 && (p->pos < len || p->run)) {
        return RTU_EINVAL; /* no room for any event: no progress possible */
    }
    const rtu_config *cfg = p->cfg;
    const rtu_chunks ch = {offsets, times, nchunks, len};
    const int timed = nchunks > 0;
    while (p->pos < len) {
        while (p->mark_index < nmarks && marks[p->mark_index].pos <= p->pos) {
            p->mark_index++;
        }
        const size_t remaining = len - (size_t)p->pos;
        size_t limit = remaining;
        if (cfg->strict) {
            /* A t3.5 silence is a hard end of frame in strict mode. */
            for (size_t m = p->mark_index; m < nmarks; m++) {
                if (marks[m].flags & RTU_MARK_T35) {
                    const size_t rel = (size_t)(marks[m].pos - p->pos);
                    if (rel < limit) {
                        limit = rel;
                    }
                    break;
                }
            }
        }
        const size_t window = limit < cfg->max_adu ? limit : cfg->max_adu;
        rtu_view v;
        v.data = data + p->pos;
        v.n = window;
        v.base = p->pos;
        v.marks = marks != NULL ? marks + p->mark_index : NULL; /* no NULL + 0 */
        v.nmarks = nmarks - p->mark_index;
        v.silent_end = window == limit;
        for (size_t m = 0; !v.silent_end && m < v.nmarks; m++) {
            const uint64_t rel = v.marks[m].pos - v.base;
            if (rel > window) {
                break;
            }
            if (rel == window && (v.marks[m].flags & RTU_MARK_T35)) {
                v.silent_end = 1;
            }
        }
        v.closed = 1;
        v.timed = timed;
        const rtu_verdict r = rtu_try_head(cfg, &p->ctx, &v, 0);
        if (r.action == RTU_ACT_DISCARD) {
            if (p->run == 0) {
                p->run_error = (uint8_t)r.error;
                p->run_start = p->pos;
            }
            p->run += (uint32_t)r.length;
            p->pos += r.length;
            p->counters.discarded[p->run_error] += r.length;
            continue;
        }
        /* closed views never wait: this is a frame, after the pending run.
         * One slot at a time, so that any capacity >= 1 makes progress: the
         * run goes out first; the frame is found again on the next call. */
        if (*nout == cap) {
            return RTU_ENOSPC;
        }
        if (p->run) {
            rtu_parser_event(p, &ch, &out[(*nout)++], p->run_start, p->run, RTU_KIND_DISCARD,
                             p->run_error);
            p->counters.discard_events++;
            p->run = 0;
            if (*nout == cap) {
                return RTU_ENOSPC;
            }
        }
        rtu_parser_event(p, &ch, &out[(*nout)++], p->pos, r.length, r.kind, RTU_ERR_NONE);
        rtu_context_update(&p->ctx, r.kind, data + p->pos);
        rtu_count_frame(&p->counters, r.kind);
        p->pos += r.length;
    }
    if (p->run) {
        if (*nout + 1 > cap) {
            return RTU_ENOSPC;
        }
        rtu_parser_event(p, &ch, &out[(*nout)++], p->run_start, p->run, RTU_KIND_DISCARD,
                         p->run_error);
        p->counters.discard_events++;
        p->run = 0;
    }
    return RTU_OK;
}
