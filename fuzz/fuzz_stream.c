/* libFuzzer harness: the bulk stream parser (csrc/rtu_stream.c, rtu_head.c,
 * rtu_predict.c) with hostile configurations, vendor rules, chunk tables with
 * extreme and non-monotonic times, and hand-made marks.
 *
 * Input: a configuration (fuzz_config), a time mode, 32 bytes of chunk/mark
 * description, a capacity byte, then the bytes to parse.
 *
 * Invariants (csrc/rtu.h): rtu_parse returns RTU_OK; events tile the input
 * (contiguous from offset 0, never two discard runs in a row); frames carry a
 * valid CRC and are 4..max_adu bytes; in strict mode no frame spans a t1.5 mark;
 * times are RTU_NO_TIME exactly when no chunks are given; the counters equal the
 * events; and parsing again with a capacity of 1..3 events, continuing after
 * each RTU_ENOSPC, makes progress on every call and gives the same events and
 * counters as the one large call. */
#include "fuzz_common.h"

#define MAX_CHUNKS 32

static void check_events(const rtu_config *cfg, const uint8_t *data, size_t len,
                         const rtu_event *ev, size_t nev, const rtu_mark *marks, size_t nmarks,
                         int timed, const rtu_counters *c)
{
    uint64_t pos = 0;
    uint64_t frames[4] = {0, 0, 0, 0};
    uint64_t discarded[RTU_NERR] = {0};
    uint64_t runs = 0;
    size_t mi = 0; /* first mark past the current event's first byte (marks ascend) */
    for (size_t i = 0; i < nev; i++) {
        const rtu_event *e = &ev[i];
        if (e->offset != pos || e->length == 0 || e->offset + e->length > len) {
            FUZZ_FAIL("event %zu at %llu+%u does not tile (expected %llu, len %zu)", i,
                      (unsigned long long)e->offset, e->length, (unsigned long long)pos, len);
        }
        fuzz_check_event(cfg, e, data + e->offset);
        if (e->kind == RTU_KIND_DISCARD) {
            if (i > 0 && ev[i - 1].kind == RTU_KIND_DISCARD) {
                FUZZ_FAIL("two discard runs in a row at %llu", (unsigned long long)e->offset);
            }
            discarded[e->error] += e->length;
            runs++;
        } else {
            frames[e->kind]++;
            while (mi < nmarks && marks[mi].pos <= e->offset) {
                mi++;
            }
            for (size_t m = mi; cfg->strict && m < nmarks && marks[m].pos < e->offset + e->length;
                 m++) {
                if (marks[m].flags & (RTU_MARK_T15 | RTU_MARK_T35)) {
                    FUZZ_FAIL("strict mode: frame at %llu spans a gap at %llu",
                              (unsigned long long)e->offset, (unsigned long long)marks[m].pos);
                }
            }
        }
        if (timed != (e->start_us != RTU_NO_TIME) || timed != (e->end_us != RTU_NO_TIME)) {
            FUZZ_FAIL("event times %lld %lld with timed=%d", (long long)e->start_us,
                      (long long)e->end_us, timed);
        }
        pos += e->length;
    }
    if (pos != len) {
        FUZZ_FAIL("events cover %llu of %zu bytes", (unsigned long long)pos, len);
    }
    if (memcmp(frames, c->frames, sizeof frames) != 0 ||
        memcmp(discarded, c->discarded, sizeof discarded) != 0 || runs != c->discard_events) {
        FUZZ_FAIL("counters differ from the events");
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    fuzz_in in = {input, size};
    static rtu_config cfg;
    fuzz_config(&in, &cfg);
    const uint8_t mode = fuzz_u8(&in) % 4; /* untimed, per-byte times, chunks, marks */
    uint8_t desc[32];
    for (size_t i = 0; i < sizeof desc; i++) {
        desc[i] = fuzz_u8(&in);
    }
    const size_t small_cap = 1 + fuzz_u8(&in) % 3;
    const uint8_t *data = in.p;
    const size_t len = in.n;

    uint64_t *offsets = NULL;
    int64_t *times = NULL;
    size_t nchunks = 0;
    rtu_mark *marks = NULL;
    size_t nmarks = 0;
    if (mode == 1 || mode == 2) {
        nchunks = mode == 1 ? len : (len > 0 ? 1 + desc[0] % MAX_CHUNKS : 0);
        offsets = malloc((nchunks + 1) * sizeof *offsets);
        times = malloc((nchunks + 1) * sizeof *times);
        fuzz_in steps = {desc + 1, sizeof desc - 1};
        int64_t now = 0;
        for (size_t c = 0; c < nchunks; c++) {
            if (steps.n == 0) {
                steps.p = desc + 1;
                steps.n = sizeof desc - 1;
            }
            /* per-byte offsets, or ascending offsets drawn from the data */
            offsets[c] = mode == 1 ? c : (c == 0 ? 0 : offsets[c - 1] + data[c % len] % 8);
            if (offsets[c] > len) {
                offsets[c] = len;
            }
            now = fuzz_time(&steps, now);
            times[c] = now;
        }
        marks = malloc((nchunks + 1) * sizeof *marks);
        if (rtu_marks_from_chunks(&cfg.timing, offsets, times, nchunks, len, marks, &nmarks) !=
            RTU_OK) {
            FUZZ_FAIL("rtu_marks_from_chunks refused a valid chunk table");
        }
        for (size_t m = 1; m < nmarks; m++) {
            if (marks[m].pos <= marks[m - 1].pos || marks[m].pos >= len) {
                FUZZ_FAIL("marks not ascending inside the data");
            }
        }
    } else if (mode == 3) {
        /* hand-made marks: ascending positions (the documented precondition),
         * any flags, some past the end */
        nmarks = desc[0] % 16;
        marks = malloc((nmarks + 1) * sizeof *marks);
        uint64_t pos = 0;
        for (size_t m = 0; m < nmarks; m++) {
            pos += 1 + desc[1 + m] % 16;
            marks[m].pos = pos;
            marks[m].flags = desc[17 + (m % 15)] % 4;
            marks[m].reserved = 0;
        }
    }
    const int timed = nchunks > 0;

    rtu_parser p;
    if (rtu_parser_init(&p, &cfg) != RTU_OK) {
        FUZZ_FAIL("rtu_parser_init refused a configuration rtu_framer_init accepts");
    }
    rtu_event *ev = malloc((len + 1) * sizeof *ev);
    size_t nev = 0;
    const int st = rtu_parse(&p, len ? data : NULL, len, marks, nmarks, offsets, times, nchunks, ev,
                             len + 1, &nev);
    if (st != RTU_OK) {
        FUZZ_FAIL("rtu_parse returned %d with room for every event", st);
    }
    check_events(&cfg, data, len, ev, nev, marks, nmarks, timed, &p.counters);

    /* again, a few events at a time */
    rtu_parser q;
    (void)rtu_parser_init(&q, &cfg);
    rtu_event *ev2 = malloc((len + 1 + small_cap) * sizeof *ev2);
    size_t got = 0;
    for (size_t calls = 0;; calls++) {
        size_t n = 0;
        const int s2 = rtu_parse(&q, len ? data : NULL, len, marks, nmarks, offsets, times, nchunks,
                                 ev2 + got, small_cap, &n);
        got += n;
        if (got > nev) {
            FUZZ_FAIL("more events in pieces (%zu) than in one call (%zu)", got, nev);
        }
        if (s2 == RTU_OK) {
            break;
        }
        if (s2 != RTU_ENOSPC || n == 0 || calls > len + 2) {
            FUZZ_FAIL("rtu_parse with capacity %zu: status %d, %zu events, call %zu", small_cap, s2,
                      n, calls);
        }
    }
    if (got != nev || memcmp(ev, ev2, nev * sizeof *ev) != 0 ||
        memcmp(&p.counters, &q.counters, sizeof p.counters) != 0) {
        FUZZ_FAIL("continuing after RTU_ENOSPC differs from one call (%zu vs %zu events)", got,
                  nev);
    }
    /* a capacity of 0 with work left is refused, not an endless RTU_ENOSPC */
    if (len > 0) {
        rtu_parser z;
        size_t n0 = 1;
        (void)rtu_parser_init(&z, &cfg);
        if (rtu_parse(&z, data, len, marks, nmarks, offsets, times, nchunks, NULL, 0, &n0) !=
                RTU_EINVAL ||
            n0 != 0) {
            FUZZ_FAIL("capacity 0 not refused");
        }
    }
    free(ev);
    free(ev2);
    free(offsets);
    free(times);
    free(marks);
    return 0;
}
