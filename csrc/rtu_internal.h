/* Internal to the C core: the step shared by the framer and the bulk parser. */
#ifndef RTU_INTERNAL_H
#define RTU_INTERNAL_H

#include "rtu.h"

/* What is known at the head of the unresolved bytes. */
typedef struct {
    const uint8_t *data;   /* the head byte */
    size_t n;              /* bytes in the window (at most max_adu) */
    uint64_t base;         /* stream position of data[0] */
    const rtu_mark *marks; /* marks with pos > base, ascending */
    size_t nmarks;
    int silent_end; /* a silence of t3.5 follows data[n - 1] */
    int closed;     /* no byte will join the window */
    int timed;      /* arrival times are known */
} rtu_view;

#define RTU_ACT_WAIT 0
#define RTU_ACT_FRAME 1
#define RTU_ACT_DISCARD 2

typedef struct {
    int action;
    size_t length; /* frame length, or bytes to discard */
    int kind;      /* RTU_KIND_* for a frame */
    int error;     /* RTU_ERR_* for a discard */
} rtu_verdict;

rtu_verdict rtu_try_head(const rtu_config *cfg, const rtu_context *ctx, const rtu_view *v,
                         int allow_skip);
/* Bytes that must still arrive before the head can end as a frame by its
 * predicted length (see rtu_framer_needed). */
size_t rtu_head_needed(const rtu_config *cfg, const rtu_context *ctx, const rtu_view *v);
void rtu_context_update(rtu_context *ctx, int kind, const uint8_t *adu);
void rtu_count_frame(rtu_counters *c, int kind);
/* The checks rtu_framer_init and rtu_parser_init share: 1 when cfg is usable. */
int rtu_config_valid(const rtu_config *cfg);

/* Time arithmetic that saturates instead of overflowing (signed overflow is
 * undefined behaviour in C99, 6.5p5).  Times live in [-INT64_MAX, INT64_MAX]:
 * INT64_MIN is RTU_NO_TIME, never a result.  The pure-Python twin clamps after
 * each step in the same order (pyrtu/core/_pure/head.py, sat_*). */
#define RTU_TIME_MIN (-INT64_MAX)

static inline int64_t rtu_time_clamp(int64_t a) { return a < RTU_TIME_MIN ? RTU_TIME_MIN : a; }

/* a + b for a, b in [-INT64_MAX, INT64_MAX], clamped to that range. */
static inline int64_t rtu_sat_add(int64_t a, int64_t b)
{
    if (b > 0 && a > INT64_MAX - b) {
        return INT64_MAX;
    }
    if (b < 0 && a < RTU_TIME_MIN - b) {
        return RTU_TIME_MIN;
    }
    return a + b;
}

static inline int64_t rtu_sat_sub(int64_t a, int64_t b) { return rtu_sat_add(a, -b); }

/* k * c for c >= 0, clamped to INT64_MAX. */
static inline int64_t rtu_sat_mul(uint64_t k, int64_t c)
{
    if (c <= 0 || k == 0) {
        return 0;
    }
    if (k > (uint64_t)(INT64_MAX / c)) {
        return INT64_MAX;
    }
    return (int64_t)k * c;
}

#endif
