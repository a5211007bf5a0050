/* libFuzzer harness for the MBAP framer and parser (csrc/rtu_mbap.c).
 *
 * Build and run (standalone; the core's sources are compiled in):
 *   clang -std=c99 -g -O1 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined \
 *         -Icsrc fuzz/fuzz_mbap.c csrc/rtu_mbap.c -o build/fuzz_mbap
 *   build/fuzz_mbap -max_total_time=60 -max_len=4096
 *
 * Input: byte 0 is the role (mod 3), byte 1 seeds the read sizes; the rest is
 * the TCP stream.  The stream is fed to the incremental framer in reads of
 * varying size (as recv() would give them), then closed, and parsed in one go
 * by rtu_mbap_parse with a tiny output array (so RTU_ENOSPC resumes are
 * exercised).  Invariants: every byte ends up in exactly one event or in the
 * post-error discard count; every frame has a valid header whose length field
 * matches its size; the framer and the parser report the same frames and the
 * same first error at the same offset; re-encoding a frame's PDU gives its
 * bytes back.  A violated invariant aborts (libFuzzer records a crash). */
#include "rtu.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define FAIL(msg)                                                                         \
    do {                                                                                  \
        fprintf(stderr, "fuzz_mbap: invariant violated at line %d: %s\n", __LINE__, msg); \
        abort();                                                                          \
    } while (0)

#define MAX_EVENTS 8192

typedef struct {
    uint64_t offset;
    uint64_t length;
    int kind;
    int error;
} ev_t;

static ev_t framed[MAX_EVENTS];
static ev_t parsed[MAX_EVENTS];

static void check_frame(const uint8_t *adu, uint64_t length, int kind, int role)
{
    size_t want = 0;
    int error = 0;
    if (length < 8 || length > RTU_MBAP_MAX_ADU) {
        FAIL("frame length outside 8..260");
    }
    if (rtu_mbap_inspect(adu, (size_t)length, &want, &error) != RTU_MBAP_COMPLETE ||
        want != length) {
        FAIL("frame does not inspect as one complete ADU");
    }
    if (rtu_mbap_kind(role, adu) != kind) {
        FAIL("frame kind differs from rtu_mbap_kind");
    }
    uint8_t out[RTU_MBAP_MAX_ADU];
    size_t n = 0;
    const uint16_t tid = (uint16_t)(adu[0] << 8 | adu[1]);
    if (rtu_mbap_encode(tid, adu[6], adu + 7, (size_t)length - 7, out, sizeof out, &n) != RTU_OK ||
        n != length || memcmp(out, adu, n) != 0) {
        FAIL("re-encoding a frame does not give its bytes back");
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size < 2) {
        return 0;
    }
    const int role = data[0] % 3;
    uint32_t seed = data[1];
    data += 2;
    size -= 2;

    static rtu_mbap_framer f;
    if (rtu_mbap_framer_init(&f, role) != RTU_OK) {
        FAIL("framer init");
    }
    size_t nframed = 0;
    uint64_t covered = 0;
    size_t pos = 0;
    while (pos < size) {
        seed = seed * 1103515245u + 12345u;
        size_t chunk = 1 + (seed >> 16) % 300;
        if (chunk > size - pos) {
            chunk = size - pos;
        }
        size_t fed = 0;
        int stalls = 0;
        while (fed < chunk) {
            const size_t took = rtu_mbap_framer_feed(&f, data + pos + fed, chunk - fed);
            fed += took;
            stalls = took ? 0 : stalls + 1;
            if (stalls > 1) {
                FAIL("the framer took nothing twice in a row");
            }
            while (rtu_mbap_framer_poll(&f)) {
                const rtu_mbap_event *e = &f.event;
                const uint8_t *at = rtu_mbap_framer_event_data(&f);
                if (at < f.buf || at + e->length > f.buf + sizeof f.buf) {
                    FAIL("event data outside the framer buffer");
                }
                if (memcmp(at, data + e->offset, (size_t)e->length) != 0) {
                    FAIL("event bytes differ from the stream");
                }
                if (e->offset != covered) {
                    FAIL("events do not tile the stream");
                }
                if (e->error == RTU_MBAP_ERR_NONE) {
                    check_frame(at, e->length, e->kind, role);
                } else if (e->kind != RTU_KIND_DISCARD) {
                    FAIL("an error event that is not a discard");
                }
                covered += e->length;
                if (nframed < MAX_EVENTS) {
                    framed[nframed++] = (ev_t){e->offset, e->length, e->kind, e->error};
                }
            }
        }
        const size_t needed = rtu_mbap_framer_needed(&f);
        if (f.error == RTU_MBAP_ERR_NONE && (needed == 0 || needed > RTU_MBAP_MAX_ADU)) {
            FAIL("needed outside 1..260 on a live stream");
        }
        pos += chunk;
    }
    rtu_mbap_framer_close(&f);
    while (rtu_mbap_framer_poll(&f)) {
        const rtu_mbap_event *e = &f.event;
        if (e->error != RTU_MBAP_ERR_TRUNCATED || e->offset != covered) {
            FAIL("end of stream gives anything but one truncated run");
        }
        covered += e->length;
        if (nframed < MAX_EVENTS) {
            framed[nframed++] = (ev_t){e->offset, e->length, e->kind, e->error};
        }
    }
    uint64_t after_error = 0;
    if (f.error != RTU_MBAP_ERR_NONE) {
        after_error = size - covered;
    } else if (covered != size) {
        FAIL("bytes lost by the framer");
    }
    uint64_t counted = 0;
    for (int r = 1; r < RTU_MBAP_NERR; r++) {
        counted += f.counters.discarded[r];
    }
    uint64_t in_frames = 0;
    for (size_t i = 0; i < nframed; i++) {
        in_frames += framed[i].error ? 0 : framed[i].length;
    }
    if (counted + in_frames != size || (after_error && counted < after_error)) {
        FAIL("discard counters do not add up");
    }

    /* The bulk parser, with a tiny output array. */
    rtu_mbap_parser p;
    if (rtu_mbap_parser_init(&p, role) != RTU_OK) {
        FAIL("parser init");
    }
    size_t nparsed = 0;
    rtu_mbap_event out[3];
    for (;;) {
        size_t n = 0;
        const int st = rtu_mbap_parse(&p, data, size, out, 3, &n);
        for (size_t i = 0; i < n && nparsed < MAX_EVENTS; i++) {
            parsed[nparsed++] = (ev_t){out[i].offset, out[i].length, out[i].kind, out[i].error};
        }
        if (st == RTU_OK) {
            break;
        }
        if (st != RTU_ENOSPC || n != 3) {
            FAIL("rtu_mbap_parse returned an unexpected status");
        }
    }
    uint64_t total = 0;
    for (size_t i = 0; i < nparsed; i++) {
        if (parsed[i].offset != total) {
            FAIL("parsed events do not tile the capture");
        }
        if (parsed[i].error == RTU_MBAP_ERR_NONE) {
            check_frame(data + parsed[i].offset, parsed[i].length, parsed[i].kind, role);
        }
        total += parsed[i].length;
    }
    if (nparsed < MAX_EVENTS && total != size) {
        FAIL("bytes lost by the parser");
    }
    /* Same frames, then the same first error at the same offset. */
    size_t i = 0;
    for (; i < nframed && i < nparsed && framed[i].error == 0 && parsed[i].error == 0; i++) {
        if (framed[i].offset != parsed[i].offset || framed[i].length != parsed[i].length ||
            framed[i].kind != parsed[i].kind) {
            FAIL("framer and parser disagree on a frame");
        }
    }
    if (i < nframed && i < nparsed &&
        (framed[i].error != parsed[i].error || framed[i].offset != parsed[i].offset)) {
        FAIL("framer and parser disagree on the first error");
    }
    if ((i < nframed) != (i < nparsed)) {
        FAIL("framer and parser disagree on the number of events");
    }
    return 0;
}
