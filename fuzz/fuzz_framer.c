/* libFuzzer harness: the incremental framer (csrc/rtu_framer.c) driven by a
 * sequence of operations -- feed (any chunking, hostile times: steps forward
 * and back, int64 extremes), poll, handle_timer, sent, reset -- on a hostile
 * configuration with vendor rules.
 *
 * Input: a configuration (fuzz_config), then operations, one byte each plus
 * their arguments; the bytes fed come from the input too.
 *
 * Invariants (csrc/rtu.h): feed takes at most what it is given and, after the
 * pending events are polled, always takes something; every event's bytes are
 * the bytes fed at its offset; frames carry a valid CRC and are 4..max_adu bytes;
 * events tile the stream (contiguous, except the bytes rtu_framer_reset drops);
 * in strict mode no frame contains a t1.5 gap; the deadline is never before the
 * last arrival; at the end a timer far enough away resolves every byte, and the
 * counters equal the events (plus the bytes reset dropped). */
#include "fuzz_common.h"

#define STREAM_MAX (1u << 16)

static uint8_t stream[STREAM_MAX]; /* every byte the framer took, by offset */

typedef struct {
    uint64_t next;   /* offset the next event must start at */
    int after_reset; /* a reset happened since the last event */
    uint64_t frames[4];
    uint64_t discard_bytes; /* in discard events */
    uint64_t dropped;       /* by rtu_framer_reset, never in an event */
    uint64_t runs;
} tally;

static void drain(rtu_framer *f, tally *t)
{
    while (rtu_framer_poll(f)) {
        const rtu_event *e = &f->event;
        const uint8_t *adu = rtu_framer_event_data(f);
        if (e->offset < t->next || (e->offset != t->next && !t->after_reset)) {
            FUZZ_FAIL("event at %llu, expected %llu", (unsigned long long)e->offset,
                      (unsigned long long)t->next);
        }
        if (e->offset + e->length > f->base + f->n || e->offset < f->base) {
            FUZZ_FAIL("event outside the buffer");
        }
        if (e->offset + e->length <= STREAM_MAX &&
            memcmp(adu, stream + e->offset, e->length) != 0) {
            FUZZ_FAIL("event bytes differ from the bytes fed at %llu",
                      (unsigned long long)e->offset);
        }
        fuzz_check_event(&f->cfg, e, adu);
        const int64_t *times = f->times + (size_t)(e->offset - f->base);
        if (e->kind == RTU_KIND_DISCARD) {
            t->discard_bytes += e->length;
            t->runs++;
        } else {
            t->frames[e->kind]++;
            for (uint32_t i = 1; f->cfg.strict && i < e->length; i++) {
                if (fuzz_is_gap(&f->cfg.timing, times[i - 1], times[i])) {
                    FUZZ_FAIL("strict mode: frame at %llu has a t1.5 gap before byte %u",
                              (unsigned long long)e->offset, i);
                }
            }
        }
        if (e->start_us == RTU_NO_TIME || e->end_us == RTU_NO_TIME) {
            FUZZ_FAIL("framer event without times");
        }
        t->next = e->offset + e->length;
        t->after_reset = 0;
    }
}

static void check_deadline(const rtu_framer *f)
{
    const int64_t d = rtu_framer_deadline(f);
    if (d != INT64_MAX && (f->last_us == RTU_NO_TIME || d < f->last_us)) {
        FUZZ_FAIL("deadline %lld before the last arrival %lld", (long long)d,
                  (long long)f->last_us);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    fuzz_in in = {input, size};
    static rtu_config cfg;
    static rtu_framer f;
    fuzz_config(&in, &cfg);
    if (rtu_framer_init(&f, &cfg) != RTU_OK) {
        FUZZ_FAIL("rtu_framer_init refused the configuration");
    }
    tally t;
    memset(&t, 0, sizeof t);
    uint64_t fed = 0;
    int64_t now = 0;
    while (in.n > 0) {
        const uint8_t op = fuzz_u8(&in);
        switch (op % 8) {
        case 0:
        case 1:
        case 2: { /* feed 1..64 bytes (or up to 1024) at one time */
            size_t len = 1 + (op >> 3) % 64;
            if (op == 0xF8) {
                len = 1 + fuzz_u16(&in) % RTU_MAX_ADU_LIMIT;
            }
            now = fuzz_time(&in, now);
            if (len > in.n) {
                len = in.n;
            }
            const uint8_t *data = in.p;
            in.p += len;
            in.n -= len;
            size_t pos = 0;
            int stalled = 0;
            while (pos < len) {
                const size_t took = rtu_framer_feed(&f, data + pos, len - pos, now);
                if (took > len - pos) {
                    FUZZ_FAIL("feed took %zu of %zu bytes", took, len - pos);
                }
                for (size_t i = 0; i < took && fed + i < STREAM_MAX; i++) {
                    stream[fed + i] = data[pos + i];
                }
                fed += took;
                pos += took;
                drain(&f, &t);
                stalled = took == 0 ? stalled + 1 : 0;
                if (stalled > 2) {
                    FUZZ_FAIL("feed makes no progress after polling");
                }
            }
            check_deadline(&f);
            break;
        }
        case 3: /* poll */
            drain(&f, &t);
            break;
        case 4: /* a timer: at the deadline, or at a hostile time */
            if (op & 8) {
                const int64_t d = rtu_framer_deadline(&f);
                if (d != INT64_MAX) {
                    now = d;
                }
            } else {
                now = fuzz_time(&in, now);
            }
            rtu_framer_handle_timer(&f, now);
            drain(&f, &t);
            check_deadline(&f);
            break;
        case 5: { /* the local side sent an ADU */
            uint8_t adu[8];
            const size_t len = fuzz_u8(&in) % 9;
            for (size_t i = 0; i < len; i++) {
                adu[i] = fuzz_u8(&in);
            }
            rtu_framer_sent(&f, len ? adu : NULL, len);
            break;
        }
        case 6: /* reset: the unresolved bytes and the pending run go, uncounted in events */
            if (op & 8) {
                t.dropped += f.n - f.head; /* counted as truncated by the reset */
                t.discard_bytes += f.run;  /* counted when discarded, never emitted */
                t.after_reset = 1;
                rtu_framer_reset(&f);
                t.next = f.base;
            }
            break;
        default: /* deadline query only */
            check_deadline(&f);
            break;
        }
    }
    /* The end: a silence longer than any flush resolves everything. */
    rtu_framer_handle_timer(&f, INT64_MAX);
    drain(&f, &t);
    if (f.n != f.head && f.last_us != RTU_NO_TIME &&
        rtu_sat_sub(INT64_MAX, f.last_us) >= f.cfg.flush_us) {
        FUZZ_FAIL("%zu bytes left unresolved after the final timer", f.n - f.head);
    }
    uint64_t discarded = 0;
    for (int e = 0; e < RTU_NERR; e++) {
        discarded += f.counters.discarded[e];
    }
    if (memcmp(t.frames, f.counters.frames, sizeof t.frames) != 0 ||
        t.runs != f.counters.discard_events) {
        FUZZ_FAIL("frame or discard-event counters differ from the events");
    }
    if (f.n == f.head && discarded != t.discard_bytes + t.dropped) {
        FUZZ_FAIL("discarded bytes %llu, events and resets give %llu",
                  (unsigned long long)discarded, (unsigned long long)(t.discard_bytes + t.dropped));
    }
    if (f.n == f.head && f.base + f.n != fed) {
        FUZZ_FAIL("stream position %llu after %llu bytes fed", (unsigned long long)(f.base + f.n),
                  (unsigned long long)fed);
    }
    return 0;
}
