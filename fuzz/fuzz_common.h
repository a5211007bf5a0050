/* Shared by the libFuzzer harnesses in fuzz/: a reader over the fuzzer's input
 * (a byte at a time from the front; past the end everything reads as zero), a
 * hostile-but-valid configuration, and the checks every harness applies.
 *
 * A violated invariant calls FUZZ_FAIL, which prints the reason and aborts, so
 * that libFuzzer records the input as a crash. */
#ifndef FUZZ_COMMON_H
#define FUZZ_COMMON_H

#include "rtu_internal.h"

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define FUZZ_FAIL(...)                                                        \
    do {                                                                      \
        fprintf(stderr, "invariant violated at %s:%d: ", __FILE__, __LINE__); \
        fprintf(stderr, __VA_ARGS__);                                         \
        fputc('\n', stderr);                                                  \
        abort();                                                              \
    } while (0)

typedef struct {
    const uint8_t *p;
    size_t n;
} fuzz_in;

static inline uint8_t fuzz_u8(fuzz_in *in)
{
    if (in->n == 0) {
        return 0;
    }
    in->n--;
    return *in->p++;
}

static inline uint16_t fuzz_u16(fuzz_in *in)
{
    const uint16_t hi = fuzz_u8(in);
    return (uint16_t)(hi << 8 | fuzz_u8(in));
}

static inline uint64_t fuzz_u64(fuzz_in *in)
{
    uint64_t v = 0;
    for (int i = 0; i < 8; i++) {
        v = v << 8 | fuzz_u8(in);
    }
    return v;
}

/* A time step or an absolute time, hostile: small and large forward steps,
 * steps backwards, and the extremes of int64 (RTU_NO_TIME included). */
static inline int64_t fuzz_time(fuzz_in *in, int64_t now)
{
    const uint8_t mode = fuzz_u8(in);
    switch (mode % 8) {
    case 0:
    case 1:
    case 2: /* a step of 0..255 x 100 us: inside frames, t1.5 and t3.5 gaps */
        return (int64_t)((uint64_t)now + (uint64_t)fuzz_u8(in) * 100u);
    case 3: /* a step of up to 65 s */
        return (int64_t)((uint64_t)now + (uint64_t)fuzz_u16(in) * 1000u);
    case 4: /* backwards */
        return (int64_t)((uint64_t)now - (uint64_t)fuzz_u16(in) * 10u);
    case 5: {
        static const int64_t extreme[8] = {INT64_MAX, INT64_MIN,     INT64_MIN + 1, -1,
                                           0,         INT64_MAX - 1, INT64_MAX / 2, INT64_MIN / 2};
        return extreme[fuzz_u8(in) % 8];
    }
    default: /* anything */
        return (int64_t)fuzz_u64(in);
    }
}

/* A configuration rtu_framer_init accepts, with hostile timing and vendor rules. */
static inline void fuzz_config(fuzz_in *in, rtu_config *cfg)
{
    const uint8_t a = fuzz_u8(in);
    const uint32_t bauds[8] = {1200, 9600, 19200, 38400, 115200, 1, 4000000, 0xFFFFFFFFu};
    if (rtu_config_init(cfg, a % 3, bauds[(a >> 2) & 7], 11, (a >> 5) & 1) != RTU_OK ||
        cfg->timing.char_us <= 0) {
        (void)rtu_config_init(cfg, a % 3, 19200, 11, RTU_TIMING_MODBUS);
    }
    cfg->strict = (a >> 6) & 1;
    const uint8_t b = fuzz_u8(in);
    if (b & 1) { /* max_adu 4..1024 */
        cfg->max_adu = 4 + fuzz_u16(in) % (RTU_MAX_ADU_LIMIT - 3);
    }
    if (b & 2) { /* hostile timing, still valid: char_us > 0, t >= 0, flush >= t3.5 */
        const int64_t pick[6] = {0, 1, 750, 1750, INT64_MAX / 4, INT64_MAX};
        cfg->timing.char_us = (b & 4) ? 1 + (int64_t)(fuzz_u16(in)) : pick[1 + fuzz_u8(in) % 5];
        cfg->timing.t15_us = pick[fuzz_u8(in) % 6];
        cfg->timing.t35_us = pick[fuzz_u8(in) % 6];
        cfg->flush_us = rtu_sat_add(cfg->timing.t35_us, fuzz_u8(in) & 1 ? 0 : 50000);
    }
    /* vendor rules: anything; rtu_rules_set must refuse what it cannot use */
    const unsigned nrules = (b >> 3) & 3;
    for (unsigned i = 0; i < nrules; i++) {
        rtu_rule r;
        r.type = fuzz_u8(in) % 5;
        r.off = fuzz_u8(in);
        r.width = fuzz_u8(in) % 4;
        r.mul = fuzz_u8(in);
        r.add = (int16_t)fuzz_u16(in);
        const int dir = (int)(fuzz_u8(in) % 3) - (b >> 7);
        const unsigned fc = fuzz_u8(in);
        const int st = rtu_rules_set(&cfg->rules, dir, fc, r);
        if (st == RTU_OK) {
            const long shortest = r.type == RTU_RULE_FIXED   ? r.add
                                  : r.type == RTU_RULE_COUNT ? (long)r.off + r.width + r.add
                                                             : 4;
            if (shortest < 4 || shortest > RTU_MAX_ADU_LIMIT || fc == 0 || fc > 127 ||
                (dir != RTU_DIR_REQUEST && dir != RTU_DIR_RESPONSE)) {
                FUZZ_FAIL("rtu_rules_set accepted type %d off %d width %d add %d dir %d fc %u",
                          r.type, r.off, r.width, r.add, dir, fc);
            }
        }
    }
}

/* The CRC of a frame, checked with the Appendix B byte loop (not the dispatcher
 * the core used). */
static inline int fuzz_crc_ok(const uint8_t *adu, size_t len)
{
    if (len < 4) {
        return 0;
    }
    const uint16_t crc = rtu_crc16_bytewise(adu, len - 2, 0xFFFF);
    return adu[len - 2] == (crc & 0xFF) && adu[len - 1] == (crc >> 8);
}

/* Per-event checks common to the framer and the parser. */
static inline void fuzz_check_event(const rtu_config *cfg, const rtu_event *e, const uint8_t *adu)
{
    if (e->kind == RTU_KIND_DISCARD) {
        if (e->error == RTU_ERR_NONE || e->error >= RTU_NERR || e->length == 0) {
            FUZZ_FAIL("discard event with error %d, length %u", e->error, e->length);
        }
        return;
    }
    if (e->kind > RTU_KIND_UNKNOWN || e->error != RTU_ERR_NONE) {
        FUZZ_FAIL("frame with kind %d error %d", e->kind, e->error);
    }
    if (e->length < 4 || e->length > cfg->max_adu) {
        FUZZ_FAIL("frame of %u bytes (max_adu %u)", e->length, cfg->max_adu);
    }
    if (!fuzz_crc_ok(adu, e->length)) {
        FUZZ_FAIL("frame at %llu (%u bytes) with a wrong CRC", (unsigned long long)e->offset,
                  e->length);
    }
    if ((adu[1] & 0x80) && e->kind != RTU_KIND_EXCEPTION) {
        FUZZ_FAIL("exception function code in a frame of kind %d", e->kind);
    }
}

/* Is the silence between two arrivals a t1.5 gap ([SL] 2.5.1.1)?  Computed as
 * the core defines it (saturating, rtu_internal.h), independently of its marks. */
static inline int fuzz_is_gap(const rtu_timing *t, int64_t prev, int64_t at)
{
    const int64_t silence = rtu_sat_sub(rtu_sat_sub(at, t->char_us), prev);
    return (t->t35_us > 0 && silence >= t->t35_us) || (t->t15_us > 0 && silence > t->t15_us);
}

#endif
