/*
 * The virtual bus's wire as a sans-I/O schedule (declared in rtu_vbus.h).
 *
 * A half-duplex two-wire line ([SL] 3.3.1): one character at a time.  Each drop's
 * queue holds (start, byte) slots one character time apart ([SL] 2.5.1: a character
 * is a start bit, the data bits, parity and stop bits); a character is delivered
 * when its last bit is sent; a character that overlaps another drop's character in
 * time collides and reaches the receivers corrupted (XOR of the two, or inverted).
 * The twin is pyrtu/core/_pure/vbus.py; the order of every step below is the twin's.
 */
#include "rtu_vbus.h"

#include <string.h>

/* every time kept here stays within +-2^62 ns (146 years), so that a character
 * time, the lead and a batch delay can be added without overflow */
#define TIME_LIMIT ((int64_t)1 << 62)
#define MAX_BATCH_NS ((int64_t)3600 * 1000000000)

static int64_t max64(int64_t a, int64_t b) { return a > b ? a : b; }

static int time_ok(int64_t t) { return t >= -TIME_LIMIT && t <= TIME_LIMIT; }

static rtu_vbus_drop *drop_at(const rtu_vbus *s, uint32_t i)
{
    if (s == NULL || s->drops == NULL || i >= s->ndrops)
        return NULL;
    return &s->drops[i];
}

static int64_t q_first_time(const rtu_vbus_drop *d) { return d->q_time[d->q_head]; }

static void q_push(rtu_vbus_drop *d, int64_t t, uint8_t b)
{
    uint32_t k = (d->q_head + d->q_len) & (RTU_VBUS_QUEUE - 1);
    d->q_time[k] = t;
    d->q_byte[k] = b;
    d->q_len++;
}

static void reset_drop(rtu_vbus_drop *d)
{
    d->q_head = d->q_len = 0;
    d->has_last = 0;
    d->hold_len = 0;
    d->hold_deadline = RTU_VBUS_NO_TIME;
    d->out_len = 0;
    d->unplug_left = -1;
    d->event_at = RTU_VBUS_NO_TIME;
    d->due = 0;
}

int rtu_vbus_init(rtu_vbus *s, rtu_vbus_drop *drops, uint32_t ndrops, int64_t char_ns,
                  int64_t lead_ns)
{
    uint32_t i;
    if (s == NULL || drops == NULL || ndrops < 1 || ndrops > RTU_VBUS_MAX_DROPS)
        return RTU_EINVAL;
    if (char_ns < 1 || char_ns > RTU_VBUS_MAX_CHAR_NS || lead_ns < 0 ||
        lead_ns > RTU_VBUS_MAX_LEAD_NS)
        return RTU_EINVAL;
    memset(s, 0, sizeof *s);
    s->drops = drops;
    s->ndrops = ndrops;
    s->char_ns = char_ns;
    s->lead_ns = lead_ns;
    s->coll_until = -1;
    for (i = 0; i < ndrops; i++) {
        rtu_vbus_drop *d = &drops[i];
        memset(d, 0, offsetof(rtu_vbus_drop, hold)); /* the buffers need no clearing */
        reset_drop(d);
        d->cut = 1;
        d->batch_bytes = 62;
        d->episode = -1;
    }
    return RTU_OK;
}

int rtu_vbus_plug(rtu_vbus *s, uint32_t drop)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL)
        return RTU_EINVAL;
    d->alive = 1;
    d->cut = 0;
    d->tx_free = 0;
    return RTU_OK;
}

int rtu_vbus_unplug(rtu_vbus *s, uint32_t drop)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL)
        return RTU_EINVAL;
    d->alive = 0;
    d->cut = 1;
    reset_drop(d);
    return RTU_OK;
}

int rtu_vbus_set_echo(rtu_vbus *s, uint32_t drop, int on)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL)
        return RTU_EINVAL;
    d->echo = on != 0;
    return RTU_OK;
}

int rtu_vbus_set_batch(rtu_vbus *s, uint32_t drop, int64_t batch_ns, uint32_t batch_bytes)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL || batch_ns < 0 || batch_ns > MAX_BATCH_NS || batch_bytes < 1 ||
        batch_bytes > RTU_VBUS_OUT)
        return RTU_EINVAL;
    d->batch_ns = batch_ns;
    d->batch_bytes = batch_bytes;
    return RTU_OK;
}

int rtu_vbus_set_unplug_after(rtu_vbus *s, uint32_t drop, int64_t left)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL)
        return RTU_EINVAL;
    d->unplug_left = left < 0 ? -1 : left;
    return RTU_OK;
}

static void cut_at(rtu_vbus_drop *d, int64_t t)
{
    d->unplug_left = -1;
    d->cut = 1;
    if (d->event_at == RTU_VBUS_NO_TIME || t < d->event_at)
        d->event_at = t;
}

int rtu_vbus_cut(rtu_vbus *s, uint32_t drop, int64_t at)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL || !time_ok(at))
        return RTU_EINVAL;
    cut_at(d, at);
    return RTU_OK;
}

int rtu_vbus_clear_hold(rtu_vbus *s, uint32_t drop)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL)
        return RTU_EINVAL;
    d->hold_len = 0;
    d->hold_deadline = RTU_VBUS_NO_TIME;
    return RTU_OK;
}

size_t rtu_vbus_space(const rtu_vbus *s, uint32_t drop)
{
    const rtu_vbus_drop *d = drop_at(s, drop);
    return d == NULL ? 0 : RTU_VBUS_QUEUE - d->q_len;
}

int rtu_vbus_transmit(rtu_vbus *s, uint32_t drop, const uint8_t *data, size_t len, int64_t now)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    int64_t c, t;
    size_t k;
    if (d == NULL || (data == NULL && len > 0) || !time_ok(now))
        return RTU_EINVAL;
    if (d->cut)
        return RTU_OK; /* a drop going away sends nothing more */
    if (len > RTU_VBUS_QUEUE - d->q_len)
        return RTU_ENOSPC;
    c = s->char_ns;
    /* Causality: the client may be answering the last byte it was given, so its
     * reply cannot start before that byte's end on the wire. */
    t = max64(now, max64(d->tx_free, d->rx_end));
    if (t > TIME_LIMIT - (int64_t)(len + 1) * c)
        return RTU_EINVAL; /* the wire would run past the clock's range */
    for (k = 0; k < len; k++) {
        if (d->unplug_left == 0) {
            cut_at(d, t);
            break;
        }
        q_push(d, t, data[k]);
        t += c;
        d->counters.tx_bytes++;
        if (d->unplug_left > 0) {
            d->unplug_left--;
            if (d->unplug_left == 0) {
                cut_at(d, t);
                break;
            }
        }
    }
    d->tx_free = t;
    return RTU_OK;
}

int64_t rtu_vbus_deadline(const rtu_vbus *s)
{
    int64_t t = RTU_VBUS_NO_TIME;
    uint32_t i;
    if (s == NULL || s->drops == NULL)
        return t;
    for (i = 0; i < s->ndrops; i++) {
        const rtu_vbus_drop *d = &s->drops[i];
        if (d->q_len > 0) {
            int64_t end = q_first_time(d) + s->char_ns;
            if (t == RTU_VBUS_NO_TIME || end < t)
                t = end;
        }
        if (d->hold_deadline != RTU_VBUS_NO_TIME && (t == RTU_VBUS_NO_TIME || d->hold_deadline < t))
            t = d->hold_deadline;
    }
    if (t != RTU_VBUS_NO_TIME)
        t -= s->lead_ns; /* deliveries are written `lead` early */
    for (i = 0; i < s->ndrops; i++) {
        int64_t e = s->drops[i].event_at;
        if (e != RTU_VBUS_NO_TIME && (t == RTU_VBUS_NO_TIME || e < t))
            t = e;
    }
    return t;
}

/* Another drop's character on the wire during [start, start + char). */
static rtu_vbus_drop *overlap(rtu_vbus *s, const rtu_vbus_drop *src, int64_t start,
                              int64_t *o_start, uint8_t *o_byte)
{
    int64_t c = s->char_ns;
    uint32_t i;
    for (i = 0; i < s->ndrops; i++) {
        rtu_vbus_drop *o = &s->drops[i];
        if (o == src)
            continue;
        if (o->has_last && start - c < o->last_start && o->last_start < start + c) {
            *o_start = o->last_start;
            *o_byte = o->last_byte;
            return o;
        }
        if (o->q_len > 0) {
            int64_t q = q_first_time(o);
            if (start - c < q && q < start + c) {
                *o_start = q;
                *o_byte = o->q_byte[o->q_head];
                return o;
            }
        }
    }
    return NULL;
}

static void out_add(rtu_vbus_drop *r, const uint8_t *data, uint32_t n)
{
    uint32_t room = RTU_VBUS_OUT - r->out_len;
    uint32_t k = n < room ? n : room;
    memcpy(r->out + r->out_len, data, k);
    r->out_len += k;
    r->counters.overruns += n - k; /* the hub could not keep it: lost, as in a full UART */
}

static void release(rtu_vbus_drop *r)
{
    out_add(r, r->hold, r->hold_len);
    r->rx_end = r->hold_end;
    r->hold_len = 0;
    r->hold_deadline = RTU_VBUS_NO_TIME;
    r->counters.batches++;
}

int rtu_vbus_service(rtu_vbus *s, int64_t now)
{
    int64_t c, horizon;
    uint32_t i;
    int due = 0;
    if (s == NULL || s->drops == NULL || !time_ok(now))
        return RTU_EINVAL;
    c = s->char_ns;
    horizon = now + s->lead_ns; /* wire time reached by what is written now */
    for (;;) {
        rtu_vbus_drop *src = NULL, *other;
        int64_t first = 0, start, end, o_start = 0;
        uint8_t value, o_byte = 0;
        for (i = 0; i < s->ndrops; i++) { /* the queued character that ends first */
            rtu_vbus_drop *d = &s->drops[i];
            if (d->q_len > 0 && (src == NULL || q_first_time(d) < first)) {
                src = d;
                first = q_first_time(d);
            }
        }
        if (src == NULL || first + c > horizon)
            break;
        start = first;
        value = src->q_byte[src->q_head];
        src->q_head = (src->q_head + 1) & (RTU_VBUS_QUEUE - 1);
        src->q_len--;
        end = start + c;
        src->last_start = start;
        src->last_byte = value;
        src->has_last = 1;
        other = overlap(s, src, start, &o_start, &o_byte);
        if (other != NULL) {
            /* what receivers see of two overlapping characters: XOR, or the
             * inverted byte when the other is 0x00 (pyrtu.vbus.collision_byte) */
            value = (uint8_t)(value ^ (o_byte ? o_byte : 0xFF));
            s->collided++;
            src->counters.collided_bytes++;
            if (start >= s->coll_until)
                s->collisions++;
            s->coll_until = max64(s->coll_until, max64(end, o_start + c));
            if (src->episode != (int64_t)s->collisions) {
                src->episode = (int64_t)s->collisions;
                src->counters.collisions++;
            }
            if (other->episode != (int64_t)s->collisions) {
                other->episode = (int64_t)s->collisions;
                other->counters.collisions++;
            }
        }
        s->wire_bytes++;
        for (i = 0; i < s->ndrops; i++) {
            rtu_vbus_drop *r = &s->drops[i];
            if (!r->alive || (r == src && !r->echo))
                continue;
            if (r->batch_ns) {
                if (r->hold_deadline != RTU_VBUS_NO_TIME && r->hold_deadline < end)
                    release(r); /* due before this byte arrived (the hub ran late) */
                if (r->hold_len == 0)
                    r->hold_deadline = end + r->batch_ns;
                r->hold[r->hold_len++] = value; /* hold_len < batch_bytes <= RTU_VBUS_OUT */
                r->hold_end = end;
                if (r->hold_len >= r->batch_bytes)
                    release(r);
            } else {
                out_add(r, &value, 1);
                r->rx_end = end;
            }
        }
    }
    for (i = 0; i < s->ndrops; i++) {
        rtu_vbus_drop *r = &s->drops[i];
        if (r->hold_deadline != RTU_VBUS_NO_TIME && r->hold_deadline <= horizon)
            release(r);
        if (r->event_at != RTU_VBUS_NO_TIME && r->event_at <= now) {
            r->event_at = RTU_VBUS_NO_TIME;
            r->due = 1;
            due++;
        }
    }
    return due;
}

int rtu_vbus_take_due(rtu_vbus *s)
{
    uint32_t i;
    if (s == NULL || s->drops == NULL)
        return -1;
    for (i = 0; i < s->ndrops; i++) {
        if (s->drops[i].due) {
            s->drops[i].due = 0;
            return (int)i;
        }
    }
    return -1;
}

int rtu_vbus_written(rtu_vbus *s, uint32_t drop, size_t n, int heard)
{
    rtu_vbus_drop *d = drop_at(s, drop);
    if (d == NULL || n > d->out_len)
        return RTU_EINVAL;
    if (heard > 0) {
        d->counters.rx_bytes += n;
        d->counters.overruns += d->out_len - n;
    } else if (heard == 0) {
        d->counters.unheard += d->out_len;
    } /* heard < 0: no pty behind the drop, nothing to count */
    d->out_len = 0;
    return RTU_OK;
}

int rtu_vbus_busy(const rtu_vbus *s)
{
    uint32_t i;
    if (s == NULL || s->drops == NULL)
        return 0;
    for (i = 0; i < s->ndrops; i++) {
        const rtu_vbus_drop *d = &s->drops[i];
        if (d->event_at != RTU_VBUS_NO_TIME || d->q_len || d->hold_len || d->out_len)
            return 1;
    }
    return 0;
}
