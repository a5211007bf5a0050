/* The sans-I/O RTU framer: bytes with their arrival time in, events out.
 *
 * Time: every byte gets an arrival time (end of its character).  Bytes that
 * arrive together at now_us are spread back over the character time, as they
 * were on the wire, but never before the previous byte.  The silence before a
 * byte is its arrival minus one character minus the previous arrival; a
 * silence longer than t1.5 or of t3.5 and more is recorded as a mark ([SL]
 * 2.5.1.1).  Strict mode closes the frame at t3.5 of silence; lenient mode
 * keeps incomplete bytes across such a gap (USB adapters batch bytes) until
 * flush_us of silence.  t3.5 = 0 (or t1.5 = 0) turns that detection off, for
 * links without wire timing (pseudo-terminals, TCP gateways).
 *
 * Times are int64 microseconds of any value but RTU_NO_TIME; the arithmetic on
 * them saturates (rtu_internal.h), so extreme or non-monotonic times shift no
 * deadline into the past and never overflow. */
#include "rtu_internal.h"

#include <string.h>

int rtu_config_init(rtu_config *c, int role, uint32_t baudrate, unsigned bits_per_char, int rule)
{
    if (c == NULL || role < RTU_ROLE_MASTER || role > RTU_ROLE_MONITOR) {
        return RTU_EINVAL;
    }
    memset(c, 0, sizeof *c);
    const int st = rtu_timing_init(&c->timing, baudrate, bits_per_char, rule);
    if (st != RTU_OK) {
        return st;
    }
    c->role = role;
    c->strict = 0;
    c->max_adu = 256; /* [SL] 2.5.1: RTU ADU of 256 bytes at most */
    c->flush_us = c->timing.t35_us > 50000 ? c->timing.t35_us : 50000;
    rtu_rules_init(&c->rules);
    return RTU_OK;
}

int rtu_config_valid(const rtu_config *c)
{
    return c->role >= RTU_ROLE_MASTER && c->role <= RTU_ROLE_MONITOR && c->max_adu >= 4 &&
           c->max_adu <= RTU_MAX_ADU_LIMIT && c->timing.char_us > 0 && c->timing.t15_us >= 0 &&
           c->timing.t35_us >= 0 && c->flush_us >= c->timing.t35_us;
}

int rtu_framer_init(rtu_framer *f, const rtu_config *cfg)
{
    if (f == NULL || cfg == NULL || !rtu_config_valid(cfg)) {
        return RTU_EINVAL;
    }
    memset(f, 0, sizeof *f);
    f->cfg = *cfg;
    f->last_us = RTU_NO_TIME;
    return RTU_OK;
}

void rtu_framer_reset(rtu_framer *f)
{
    if (f->n > f->head) {
        f->counters.discarded[RTU_ERR_TRUNCATED] += f->n - f->head;
    }
    f->base += f->n;
    f->n = f->head = 0;
    f->nmarks = 0;
    f->run = 0;
    f->silent = f->final = 0;
    f->ctx.pending = 0;
}

/* Forget the bytes before `keep` (the last event has been read). */
static void rtu_framer_compact(rtu_framer *f, size_t keep)
{
    if (keep == 0) {
        return;
    }
    const size_t left = f->n - keep;
    memmove(f->buf, f->buf + keep, left);
    memmove(f->times, f->times + keep, left * sizeof f->times[0]);
    f->base += keep;
    f->n = left;
    f->head -= keep;
    size_t m = 0;
    while (m < f->nmarks && f->marks[m].pos <= f->base) {
        m++;
    }
    if (m > 0) {
        memmove(f->marks, f->marks + m, (f->nmarks - m) * sizeof f->marks[0]);
        f->nmarks -= m;
    }
}

size_t rtu_framer_feed(rtu_framer *f, const uint8_t *data, size_t len, int64_t now_us)
{
    rtu_framer_compact(f, f->head);
    if (data == NULL || (f->final && f->n > f->head)) {
        return 0; /* poll first (or nothing to take) */
    }
    const rtu_timing *t = &f->cfg.timing;
    now_us = rtu_time_clamp(now_us);
    size_t i = 0;
    for (; i < len && f->n < RTU_FRAMER_CAP; i++) {
        int64_t at = rtu_sat_sub(now_us, rtu_sat_mul(len - 1 - i, t->char_us));
        uint32_t flags = 0;
        if (f->last_us != RTU_NO_TIME) {
            if (at < f->last_us) {
                at = f->last_us;
            }
            const int64_t silence = rtu_sat_sub(rtu_sat_sub(at, t->char_us), f->last_us);
            if (t->t35_us > 0 && silence >= t->t35_us) {
                const int closes = f->cfg.strict || silence >= f->cfg.flush_us;
                if (f->n > f->head && (!f->silent || (closes && !f->final))) {
                    /* The silence ends what is buffered: resolve it first. */
                    f->silent = 1;
                    f->final = closes;
                    return i;
                }
                flags = RTU_MARK_T15 | RTU_MARK_T35;
            } else if (t->t15_us > 0 && silence > t->t15_us) {
                flags = RTU_MARK_T15;
            }
        }
        if (flags && f->n > f->head) {
            f->marks[f->nmarks].pos = f->base + f->n;
            f->marks[f->nmarks].flags = flags;
            f->nmarks++;
        }
        f->silent = 0;
        f->final = 0;
        f->buf[f->n] = data[i];
        f->times[f->n] = at;
        f->last_us = at;
        f->n++;
    }
    return i;
}

void rtu_framer_handle_timer(rtu_framer *f, int64_t now_us)
{
    if (f->n <= f->head || f->last_us == RTU_NO_TIME) {
        return;
    }
    const int64_t silence = rtu_sat_sub(rtu_time_clamp(now_us), f->last_us);
    if (silence >= f->cfg.timing.t35_us) {
        f->silent = 1;
        if (f->cfg.strict || silence >= f->cfg.flush_us) {
            f->final = 1;
        }
    }
}

int64_t rtu_framer_deadline(const rtu_framer *f)
{
    if (f->n <= f->head || f->last_us == RTU_NO_TIME) {
        return INT64_MAX;
    }
    if (!f->silent) {
        return rtu_sat_add(f->last_us, f->cfg.timing.t35_us);
    }
    if (!f->final) {
        return rtu_sat_add(f->last_us, f->cfg.flush_us);
    }
    return INT64_MAX;
}

static void rtu_framer_emit(rtu_framer *f, size_t at, size_t len, int kind, int error)
{
    rtu_event *e = &f->event;
    e->offset = f->base + at;
    e->length = (uint32_t)len;
    e->kind = (uint8_t)kind;
    e->error = (uint8_t)error;
    e->reserved = 0;
    e->start_us = rtu_sat_sub(f->times[at], f->cfg.timing.char_us);
    e->end_us = f->times[at + len - 1];
}

static int rtu_framer_emit_run(rtu_framer *f)
{
    rtu_framer_emit(f, f->head - f->run, f->run, RTU_KIND_DISCARD, f->run_error);
    f->counters.discard_events++;
    f->run = 0;
    return 1;
}

/* The window at the head of the unresolved bytes (at most max_adu) with the silence
 * marks after its start: what rtu_try_head and rtu_head_needed look at. */
static void rtu_framer_head_view(const rtu_framer *f, rtu_view *v)
{
    const size_t unresolved = f->n - f->head;
    v->data = f->buf + f->head;
    v->n = unresolved < f->cfg.max_adu ? unresolved : f->cfg.max_adu;
    v->base = f->base + f->head;
    size_t m = 0;
    while (m < f->nmarks && f->marks[m].pos <= v->base) {
        m++;
    }
    v->marks = f->marks + m;
    v->nmarks = f->nmarks - m;
    v->silent_end = f->silent && v->n == unresolved;
    v->closed = f->final || v->n < unresolved;
    v->timed = 1;
}

int rtu_framer_poll(rtu_framer *f)
{
    rtu_framer_compact(f, f->head);
    for (;;) {
        const size_t unresolved = f->n - f->head;
        if (unresolved == 0) {
            f->silent = f->final = 0;
            return f->run ? rtu_framer_emit_run(f) : 0;
        }
        rtu_view v;
        rtu_framer_head_view(f, &v);
        const rtu_verdict r = rtu_try_head(&f->cfg, &f->ctx, &v, 1);
        if (r.action == RTU_ACT_DISCARD) {
            if (f->run == 0) {
                f->run_error = (uint8_t)r.error;
            }
            f->run += (uint32_t)r.length;
            f->head += r.length;
            f->counters.discarded[f->run_error] += r.length;
            continue;
        }
        if (f->run) {
            return rtu_framer_emit_run(f);
        }
        if (r.action == RTU_ACT_WAIT) {
            return 0;
        }
        rtu_framer_emit(f, f->head, r.length, r.kind, RTU_ERR_NONE);
        rtu_context_update(&f->ctx, r.kind, f->buf + f->head);
        rtu_count_frame(&f->counters, r.kind);
        f->head += r.length;
        return 1;
    }
}

const uint8_t *rtu_framer_event_data(const rtu_framer *f)
{
    return f->buf + (size_t)(f->event.offset - f->base);
}

void rtu_framer_sent(rtu_framer *f, const uint8_t *adu, size_t len)
{
    if (f->cfg.role == RTU_ROLE_MASTER && adu != NULL && len >= 2 && adu[0] != 0) {
        f->ctx.pending = 1;
        f->ctx.address = adu[0];
        f->ctx.function = adu[1];
    } else {
        f->ctx.pending = 0;
    }
}

size_t rtu_framer_needed(const rtu_framer *f)
{
    rtu_view v;
    rtu_framer_head_view(f, &v);
    return rtu_head_needed(&f->cfg, &f->ctx, &v);
}
