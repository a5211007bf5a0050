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

#endif
