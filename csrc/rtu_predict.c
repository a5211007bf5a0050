/* Frame-length prediction, in steps as libmodbus does (function -> meta ->
 * data): the function code selects a rule, the rule says where the length
 * information sits, and the length follows from it.  Lengths are whole ADUs:
 * address (1) + PDU + CRC (2), [SL] 2.5.1.
 *
 * PDU layouts from [AP] section 6 (request / response):
 *   01, 02  read bits            8 / 5 + byte count [2]
 *   03, 04  read registers       8 / 5 + byte count [2]
 *   05, 06  write single         8 / 8
 *   07      read exception st.   4 / 5
 *   08      diagnostics          8 / 8 (serial-line sub-functions, [SL] and [AP] 6.8.1)
 *   11      comm event counter   4 / 8
 *   12      comm event log       4 / 5 + byte count [2]
 *   15, 16  write multiple       9 + byte count [6] / 8
 *   17      report server id     4 / 5 + byte count [2]
 *   20, 21  file record          5 + byte count [2] / 5 + byte count [2]
 *   22      mask write register  10 / 10
 *   23      read/write registers 13 + byte count [10] / 5 + byte count [2]
 *   24      read FIFO queue      6 / 6 + byte count [2..3] (16 bits)
 *   43/14   device id            7 / walk of the objects ([AP] 6.21)
 * Exception responses (function | 0x80) are 5 bytes ([AP] 7). */
#include "rtu.h"

#include <string.h>

static rtu_rule rtu_fixed(int16_t len)
{
    rtu_rule r = {RTU_RULE_FIXED, 0, 0, 0, len};
    return r;
}

static rtu_rule rtu_count(uint8_t off, uint8_t width, int16_t add)
{
    rtu_rule r = {RTU_RULE_COUNT, off, width, 1, add};
    return r;
}

void rtu_rules_init(rtu_rules *r)
{
    memset(r, 0, sizeof *r);
    rtu_rule *q = r->rule[RTU_DIR_REQUEST];
    rtu_rule *s = r->rule[RTU_DIR_RESPONSE];
    for (unsigned fc = 1; fc <= 4; fc++) {
        q[fc] = rtu_fixed(8);
        s[fc] = rtu_count(2, 1, 2);
    }
    q[5] = q[6] = s[5] = s[6] = rtu_fixed(8);
    q[7] = rtu_fixed(4);
    s[7] = rtu_fixed(5);
    q[8] = s[8] = rtu_fixed(8);
    q[11] = rtu_fixed(4);
    s[11] = rtu_fixed(8);
    q[12] = rtu_fixed(4);
    s[12] = rtu_count(2, 1, 2);
    q[15] = q[16] = rtu_count(6, 1, 2);
    s[15] = s[16] = rtu_fixed(8);
    q[17] = rtu_fixed(4);
    s[17] = rtu_count(2, 1, 2);
    q[20] = q[21] = s[20] = s[21] = rtu_count(2, 1, 2);
    q[22] = s[22] = rtu_fixed(10);
    q[23] = rtu_count(10, 1, 2);
    s[23] = rtu_count(2, 1, 2);
    q[24] = rtu_fixed(6);
    s[24] = rtu_count(2, 2, 2);
    q[43].type = s[43].type = RTU_RULE_MEI;
}

int rtu_rules_set(rtu_rules *r, int direction, unsigned function, rtu_rule rule)
{
    if (r == NULL || (direction != RTU_DIR_REQUEST && direction != RTU_DIR_RESPONSE)) {
        return RTU_EINVAL;
    }
    /* Codes 128-255 are exception responses ([AP] 7); 0 is not a function. */
    if (function == 0 || function > 127 || rule.type > RTU_RULE_MEI) {
        return RTU_EINVAL;
    }
    if (rule.type == RTU_RULE_FIXED && (rule.add < 4 || rule.add > RTU_MAX_ADU_LIMIT)) {
        return RTU_EINVAL;
    }
    /* A count rule's shortest ADU (count 0) obeys the bounds of a fixed one:
     * address, function and CRC make 4 bytes at least ([SL] 2.5.1). */
    if (rule.type == RTU_RULE_COUNT &&
        (rule.off < 2 || (rule.width != 1 && rule.width != 2) || rule.mul == 0 || rule.add < 0 ||
         rule.off + rule.width + rule.add < 4 ||
         rule.off + rule.width + rule.add > RTU_MAX_ADU_LIMIT)) {
        return RTU_EINVAL;
    }
    r->rule[direction][function] = rule;
    return RTU_OK;
}

/* [AP] 6.21, Read Device Identification response: address, 0x2B, MEI 0x0E,
 * read code, conformity, more follows, next object id, number of objects
 * (8 bytes with the address), then per object id, length, value; then CRC. */
static int rtu_predict_mei_response(const uint8_t *adu, size_t n, size_t *length)
{
    if (n < 3) {
        *length = 3;
        return RTU_PRED_NEED;
    }
    if (adu[2] != 0x0E) {
        return RTU_PRED_UNKNOWN;
    }
    if (n < 8) {
        *length = 8;
        return RTU_PRED_NEED;
    }
    size_t pos = 8;
    for (unsigned obj = 0; obj < adu[7]; obj++) {
        if (n < pos + 2) {
            *length = pos + 2;
            return RTU_PRED_NEED;
        }
        pos += 2u + adu[pos + 1];
        if (pos > RTU_MAX_ADU_LIMIT) {
            break; /* longer than any ADU: the caller reports overflow */
        }
    }
    *length = pos + 2;
    return RTU_PRED_LENGTH;
}

int rtu_predict(const rtu_rules *r, int direction, const uint8_t *adu, size_t n, size_t *length)
{
    if (direction != RTU_DIR_REQUEST && direction != RTU_DIR_RESPONSE) {
        return RTU_PRED_UNKNOWN; /* rule[direction] would be out of bounds */
    }
    if (n < 2) {
        *length = 2;
        return RTU_PRED_NEED;
    }
    const uint8_t fc = adu[1];
    if (fc & 0x80) { /* exception response: address, fc | 0x80, code, CRC */
        if (direction != RTU_DIR_RESPONSE) {
            return RTU_PRED_UNKNOWN;
        }
        *length = 5;
        return RTU_PRED_LENGTH;
    }
    const rtu_rule *rule = &r->rule[direction][fc];
    switch (rule->type) {
    case RTU_RULE_FIXED:
        *length = (size_t)rule->add;
        return RTU_PRED_LENGTH;
    case RTU_RULE_COUNT: {
        const size_t meta = (size_t)rule->off + rule->width;
        if (n < meta) {
            *length = meta;
            return RTU_PRED_NEED;
        }
        size_t count = adu[rule->off];
        if (rule->width == 2) {
            count = (count << 8) | adu[rule->off + 1];
        }
        *length = meta + count * rule->mul + (size_t)rule->add;
        return RTU_PRED_LENGTH;
    }
    case RTU_RULE_MEI:
        if (direction == RTU_DIR_RESPONSE) {
            return rtu_predict_mei_response(adu, n, length);
        }
        if (n < 3) {
            *length = 3;
            return RTU_PRED_NEED;
        }
        if (adu[2] != 0x0E) {
            return RTU_PRED_UNKNOWN;
        }
        *length = 7;
        return RTU_PRED_LENGTH;
    default:
        return RTU_PRED_UNKNOWN;
    }
}
