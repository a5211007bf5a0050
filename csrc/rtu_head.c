/* Resolving the head of the unresolved bytes: frame, wait, or discard.
 *
 * [SL] 2.5.1.1: a frame is delimited by silences of t3.5; a silence longer
 * than t1.5 inside it makes it incomplete (strict mode discards it).  [SL]
 * 2.5.1.2 / 6.2.2: the CRC decides whether the bytes form a frame.  The
 * length is predicted from the function code ([AP] section 6) so that a frame
 * ends as soon as it is complete and its CRC checks, without waiting for the
 * silence, and so that frames that share a burst (USB adapters batch bytes)
 * are still split.
 *
 * Candidates, in order: the predicted lengths (for the expected direction
 * first), then the silence-delimited lengths.  The first candidate whose CRC
 * checks is the frame.  If none does and one may still complete, wait;
 * otherwise discard one byte, so that the caller slides to the next position
 * where a valid frame starts. */
#include "rtu_internal.h"

#define NOTE_CRC 1
#define NOTE_T15 2
#define NOTE_OVERFLOW 4
#define NOTE_TRUNCATED 8
#define NOTE_UNKNOWN 16

static int rtu_crc_ok(const uint8_t *adu, size_t len)
{
    const uint16_t crc = rtu_crc16(adu, len - 2, 0xFFFF);
    /* [CFW] 4.2.4: the low byte of the CRC is sent first. */
    return adu[len - 2] == (uint8_t)(crc & 0xFF) && adu[len - 1] == (uint8_t)(crc >> 8);
}

/* A silence longer than t1.5 between two bytes of data[0..len). */
static int rtu_has_gap(const rtu_view *v, size_t len)
{
    for (size_t i = 0; i < v->nmarks; i++) {
        const uint64_t rel = v->marks[i].pos - v->base;
        if (rel >= len) {
            break;
        }
        if (rel > 0 && (v->marks[i].flags & RTU_MARK_T15)) {
            return 1;
        }
    }
    return 0;
}

static int rtu_context_match(const rtu_context *ctx, const uint8_t *adu)
{
    return ctx->pending && adu[0] == ctx->address && (adu[1] & 0x7F) == ctx->function;
}

static int rtu_silence_kind(const rtu_config *cfg, const rtu_context *ctx, const uint8_t *adu)
{
    if (adu[1] & 0x80) {
        return RTU_KIND_EXCEPTION;
    }
    if (cfg->role == RTU_ROLE_MASTER || rtu_context_match(ctx, adu)) {
        return RTU_KIND_RESPONSE;
    }
    if (cfg->role == RTU_ROLE_SLAVE ||
        cfg->rules.rule[RTU_DIR_REQUEST][adu[1]].type != RTU_RULE_NONE) {
        return RTU_KIND_REQUEST;
    }
    return RTU_KIND_UNKNOWN;
}

/* The strongest evidence first: a CRC that checks across a gap, a length
 * field past the limit, a failing CRC, too few bytes, an unknown function. */
static int rtu_pick_error(unsigned notes)
{
    if (notes & NOTE_T15) {
        return RTU_ERR_T15;
    }
    if (notes & NOTE_OVERFLOW) {
        return RTU_ERR_OVERFLOW;
    }
    if (notes & NOTE_CRC) {
        return RTU_ERR_CRC;
    }
    if (notes & NOTE_TRUNCATED) {
        return RTU_ERR_TRUNCATED;
    }
    if (notes & NOTE_UNKNOWN) {
        return RTU_ERR_UNKNOWN_FUNCTION;
    }
    return RTU_ERR_TRUNCATED;
}

static rtu_verdict rtu_verdict_of(int action, size_t length, int kind, int error)
{
    rtu_verdict v = {action, length, kind, error};
    return v;
}

/* A running CRC over data[0..done): candidates checked in ascending length
 * extend it instead of starting over, so that a window with many t3.5 marks
 * costs one pass over its bytes, not one per mark (a hostile capture could
 * otherwise cost max_adu^2 CRC bytes per input byte). */
typedef struct {
    size_t done;
    uint16_t crc;
} rtu_crc_run;

static int rtu_crc_ok_run(const uint8_t *adu, size_t len, rtu_crc_run *run)
{
    if (run == NULL || len - 2 < run->done) {
        return rtu_crc_ok(adu, len);
    }
    run->crc = rtu_crc16(adu + run->done, len - 2 - run->done, run->crc);
    run->done = len - 2;
    /* [CFW] 4.2.4: the low byte of the CRC is sent first. */
    return adu[len - 2] == (uint8_t)(run->crc & 0xFF) && adu[len - 1] == (uint8_t)(run->crc >> 8);
}

/* Check one candidate length; returns 1 when it is a frame. */
static int rtu_check(const rtu_config *cfg, const rtu_view *v, size_t len, unsigned *notes,
                     rtu_crc_run *run)
{
    if (len < 4) {
        *notes |= NOTE_TRUNCATED;
        return 0;
    }
    if (!rtu_crc_ok_run(v->data, len, run)) {
        *notes |= NOTE_CRC;
        return 0;
    }
    if (cfg->strict && rtu_has_gap(v, len)) {
        *notes |= NOTE_T15;
        return 0;
    }
    return 1;
}

rtu_verdict rtu_try_head(const rtu_config *cfg, const rtu_context *ctx, const rtu_view *v,
                         int allow_skip)
{
    const size_t n = v->n;
    const uint8_t *d = v->data;
    unsigned pnotes[2] = {0, 0}; /* why each predicted candidate failed */
    unsigned notes = 0;          /* why the silence-delimited candidates failed */
    int can_wait = 0;

    if (n < 2) {
        if (v->closed) {
            return rtu_verdict_of(RTU_ACT_DISCARD, 1, 0, RTU_ERR_TRUNCATED);
        }
        return rtu_verdict_of(RTU_ACT_WAIT, 0, 0, 0);
    }

    /* 1. Predicted lengths, expected direction first. */
    int kinds[2];
    int nk;
    if ((d[1] & 0x80) || cfg->role == RTU_ROLE_MASTER) {
        kinds[0] = RTU_KIND_RESPONSE;
        nk = 1;
    } else if (rtu_context_match(ctx, d)) {
        kinds[0] = RTU_KIND_RESPONSE;
        kinds[1] = RTU_KIND_REQUEST;
        nk = 2;
    } else {
        kinds[0] = RTU_KIND_REQUEST;
        kinds[1] = RTU_KIND_RESPONSE;
        nk = 2;
    }
    for (int k = 0; k < nk; k++) {
        const int dir = kinds[k] == RTU_KIND_REQUEST ? RTU_DIR_REQUEST : RTU_DIR_RESPONSE;
        size_t len = 0;
        const int st = rtu_predict(&cfg->rules, dir, d, n, &len);
        if (st == RTU_PRED_UNKNOWN) {
            pnotes[k] = NOTE_UNKNOWN;
            continue;
        }
        if (len > cfg->max_adu) {
            pnotes[k] = NOTE_OVERFLOW;
            continue;
        }
        if (st == RTU_PRED_NEED || len > n) {
            can_wait = 1;
            pnotes[k] = NOTE_TRUNCATED;
            continue;
        }
        if (rtu_check(cfg, v, len, &pnotes[k], NULL)) {
            const int kind = (d[1] & 0x80) ? RTU_KIND_EXCEPTION : kinds[k];
            return rtu_verdict_of(RTU_ACT_FRAME, len, kind, 0);
        }
    }

    /* 2. Silence-delimited lengths ([SL] 2.5.1.1): every t3.5 boundary in the
     * window (strict mode: only the first), then the end if silence follows.
     * Lenient mode keeps bytes across a gap that does not close the frame: while
     * a predicted length is still to come, the header says the frame goes on,
     * and a CRC that happens to check on a shorter prefix (1 in 65536) must not
     * cut it (it is a frame once the silence closes, or never). */
    int stop = can_wait && !cfg->strict && !v->closed;
    rtu_crc_run run = {0, 0xFFFF}; /* the marks ascend, and n is past them all */
    for (size_t i = 0; !stop && i < v->nmarks; i++) {
        const uint64_t rel = v->marks[i].pos - v->base;
        if (rel >= n) {
            break;
        }
        if (!(v->marks[i].flags & RTU_MARK_T35)) {
            continue;
        }
        if (rtu_check(cfg, v, (size_t)rel, &notes, &run)) {
            return rtu_verdict_of(RTU_ACT_FRAME, (size_t)rel, rtu_silence_kind(cfg, ctx, d), 0);
        }
        if (cfg->strict) {
            stop = 1;
            break;
        }
    }
    if (!stop && v->silent_end && rtu_check(cfg, v, n, &notes, &run)) {
        return rtu_verdict_of(RTU_ACT_FRAME, n, rtu_silence_kind(cfg, ctx, d), 0);
    }

    /* 3. Wait, when a candidate may still complete or a silence may still
     * delimit the head; but a valid frame right after a t3.5 gap wins over an
     * incomplete one before it (lenient mode keeps bytes across gaps). */
    if (!v->closed && (can_wait || (v->timed && !v->silent_end && n <= cfg->max_adu))) {
        for (size_t i = 0; allow_skip && i < v->nmarks; i++) {
            const uint64_t rel = v->marks[i].pos - v->base;
            if (rel >= n) {
                break;
            }
            if (rel == 0 || !(v->marks[i].flags & RTU_MARK_T35)) {
                continue;
            }
            rtu_view sub = *v;
            sub.data = d + rel;
            sub.n = n - (size_t)rel;
            sub.base = v->base + rel;
            sub.marks = v->marks + i + 1;
            sub.nmarks = v->nmarks - i - 1;
            const rtu_verdict r = rtu_try_head(cfg, ctx, &sub, 0);
            if (r.action == RTU_ACT_FRAME) {
                return rtu_verdict_of(RTU_ACT_DISCARD, (size_t)rel, 0, RTU_ERR_TRUNCATED);
            }
        }
        return rtu_verdict_of(RTU_ACT_WAIT, 0, 0, 0);
    }
    /* The predicted candidates give the reason; the silence's only without them. */
    const unsigned reason = (pnotes[0] | pnotes[1]) ? (pnotes[0] | pnotes[1]) : notes;
    return rtu_verdict_of(RTU_ACT_DISCARD, 1, 0, rtu_pick_error(reason));
}

void rtu_context_update(rtu_context *ctx, int kind, const uint8_t *adu)
{
    if (kind == RTU_KIND_REQUEST && adu[0] != 0) {
        ctx->pending = 1;
        ctx->address = adu[0];
        ctx->function = adu[1];
    } else {
        /* A response ends the transaction; a broadcast expects none ([SL] 2.1). */
        ctx->pending = 0;
    }
}

void rtu_count_frame(rtu_counters *c, int kind)
{
    if (kind >= 0 && kind < 4) {
        c->frames[kind]++;
    }
}

/* ---- Bytes still needed: the lower bound a driver may sleep on ----------- */

/* The shortest frame of direction `dir` that starts with d[0..n) (n >= 2), from
 * the prediction rules ([AP] section 6); 0 when no rule predicts it.  Before a
 * count field is in, a count of zero gives the bound; before the rest of a
 * Device Identification walk is in, the CRC after the decision point does. */
static size_t rtu_min_length(const rtu_rules *r, int dir, const uint8_t *d, size_t n)
{
    size_t len = 0;
    const int st = rtu_predict(r, dir, d, n, &len);
    if (st == RTU_PRED_UNKNOWN) {
        return 0;
    }
    if (st == RTU_PRED_NEED) {
        const rtu_rule *rule = &r->rule[dir][d[1]];
        return rule->type == RTU_RULE_COUNT ? len + (size_t)rule->add : len + 2;
    }
    return len;
}

size_t rtu_answer_min(const rtu_rules *r, uint8_t address, uint8_t function)
{
    const uint8_t d[2] = {address, (uint8_t)(function & 0x7F)};
    const size_t len = rtu_min_length(r, RTU_DIR_RESPONSE, d, 2);
    if (len == 0) {
        return 4; /* unknown layout: the shortest RTU frame ([SL] 2.5.1) */
    }
    return len < 5 ? len : 5; /* or an exception response, 5 bytes ([AP] 7) */
}

size_t rtu_head_needed(const rtu_config *cfg, const rtu_context *ctx, const rtu_view *v)
{
    const size_t n = v->n;
    const uint8_t *d = v->data;
    size_t least = 0;
    if (n < 2) {
        if (cfg->role == RTU_ROLE_MASTER && ctx->pending && (n == 0 || d[0] == ctx->address)) {
            least = rtu_answer_min(&cfg->rules, ctx->address, ctx->function);
        } else if (n == 1) {
            least = 2; /* the function code decides */
        }
    } else {
        int dirs[2];
        int nd;
        if ((d[1] & 0x80) || cfg->role == RTU_ROLE_MASTER) {
            dirs[0] = RTU_DIR_RESPONSE;
            nd = 1;
        } else {
            dirs[0] = RTU_DIR_REQUEST;
            dirs[1] = RTU_DIR_RESPONSE;
            nd = 2;
        }
        for (int k = 0; k < nd; k++) {
            const size_t len = rtu_min_length(&cfg->rules, dirs[k], d, n);
            if (len > n && len <= cfg->max_adu && (least == 0 || len < least)) {
                least = len;
            }
        }
    }
    size_t need = least > n ? least - n : 0;
    /* A frame that starts after a t3.5 silence inside the window may end first
     * (rtu_try_head lets it win over an incomplete one before it). */
    for (size_t i = 0; i < v->nmarks; i++) {
        const uint64_t rel = v->marks[i].pos - v->base;
        if (rel >= n) {
            break;
        }
        if (rel == 0 || !(v->marks[i].flags & RTU_MARK_T35)) {
            continue;
        }
        rtu_view sub = *v;
        sub.data = d + rel;
        sub.n = n - (size_t)rel;
        sub.base = v->base + rel;
        sub.marks = v->marks + i + 1;
        sub.nmarks = v->nmarks - i - 1;
        const size_t s = rtu_head_needed(cfg, ctx, &sub);
        if (s != 0 && (need == 0 || s < need)) {
            need = s;
        }
        break; /* the sub-view covers the later marks */
    }
    return need;
}
