/* libFuzzer harness: frame-length prediction (csrc/rtu_predict.c) with hostile
 * vendor rules and directions, fed one more byte at a time as a framer sees an
 * ADU arrive.
 *
 * Input: up to 8 rules (type, off, width, mul, add, direction, function: any
 * values; rtu_rules_set must refuse what it cannot use), a direction (any int),
 * then the ADU bytes.
 *
 * Invariants: rtu_predict returns one of the three RTU_PRED_* codes and reads
 * only the n bytes it is given (ASan); an out-of-range direction is
 * RTU_PRED_UNKNOWN; RTU_PRED_NEED asks for more than n bytes; a rule that
 * rtu_rules_set accepted never predicts an ADU under 4 bytes; once a length is
 * predicted, more bytes predict the same length; once the function is unknown it
 * stays unknown. */
#include "fuzz_common.h"

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    fuzz_in in = {input, size};
    static rtu_rules rules;
    rtu_rules_init(&rules);
    const unsigned nrules = fuzz_u8(&in) % 9;
    for (unsigned i = 0; i < nrules; i++) {
        rtu_rule r;
        r.type = fuzz_u8(&in);
        r.off = fuzz_u8(&in);
        r.width = fuzz_u8(&in);
        r.mul = fuzz_u8(&in);
        r.add = (int16_t)fuzz_u16(&in);
        const int dir = (int)(int8_t)fuzz_u8(&in);
        const unsigned fc = fuzz_u8(&in) | (unsigned)(fuzz_u8(&in) & 1) << 8;
        (void)rtu_rules_set(&rules, dir, fc, r);
    }
    const int8_t d = (int8_t)fuzz_u8(&in);
    const int dir = d == 2 ? INT32_MAX : d == 3 ? INT32_MIN : d;
    const size_t len = in.n;
    /* an exact copy, so that ASan sees any read past the n bytes given */
    uint8_t *adu = malloc(len ? len : 1);
    memcpy(adu, in.p, len);
    int decided = -1;
    size_t decided_len = 0;
    for (size_t n = 0; n <= len; n++) {
        size_t length = 0;
        const int st = rtu_predict(&rules, dir, n ? adu : NULL, n, &length);
        if (st != RTU_PRED_LENGTH && st != RTU_PRED_NEED && st != RTU_PRED_UNKNOWN) {
            FUZZ_FAIL("rtu_predict returned %d", st);
        }
        if (dir != RTU_DIR_REQUEST && dir != RTU_DIR_RESPONSE && st != RTU_PRED_UNKNOWN) {
            FUZZ_FAIL("direction %d predicted (%d)", dir, st);
        }
        if (st == RTU_PRED_NEED && length <= n) {
            FUZZ_FAIL("NEED %zu bytes with %zu present", length, n);
        }
        if (st == RTU_PRED_LENGTH && length < 4) {
            FUZZ_FAIL("predicted ADU of %zu bytes", length);
        }
        if (decided == RTU_PRED_LENGTH && (st != RTU_PRED_LENGTH || length != decided_len)) {
            FUZZ_FAIL("prediction changed from %zu bytes to %d/%zu at n=%zu", decided_len, st,
                      length, n);
        }
        if (decided == RTU_PRED_UNKNOWN && st != RTU_PRED_UNKNOWN) {
            FUZZ_FAIL("unknown function became known at n=%zu", n);
        }
        if (st != RTU_PRED_NEED) {
            decided = st;
            decided_len = length;
        }
    }
    free(adu);
    return 0;
}
