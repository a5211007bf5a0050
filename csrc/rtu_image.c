/*
 * The image of a DataStore (declared in rtu_image.h): plain reads answered from
 * the caller's copy of the values, byte for byte as pyrtu's Python slave answers
 * them (pyrtu/drivers/slave_base.py _read_bits / _read_registers over
 * pyrtu/pdu/base.py decode_read, bits_response, registers_response).
 *
 * [AP] MODBUS Application Protocol Specification V1.1b3:
 *   6.1 Read Coils (FC 01), 6.2 Read Discrete Inputs (FC 02): request function,
 *       starting address (2 bytes), quantity of bits 1..2000 (0x7D0); response
 *       function, byte count N = ceil(quantity / 8), the bits packed LSB first of
 *       the first byte = the first address, the unused high bits of the last
 *       byte 0;
 *   6.3 Read Holding Registers (FC 03), 6.4 Read Input Registers (FC 04):
 *       request function, starting address, quantity of registers 1..125 (0x7D);
 *       response function, byte count 2 x quantity, each register big-endian.
 * Every other case (a PDU of another length, quantity 0 or past the limit,
 * address + quantity past 65536, an address outside every range, a held range)
 * is Python's: it answers the exception with its own counters, or calls the
 * range's on_read.  The twin is pyrtu/core/_pure/image.py.
 */
#include "rtu_image.h"

#include <string.h>

#define ADDRESSES 65536u
#define MAX_BITS 2000u     /* [AP] 6.1, 6.2: quantity 1..0x7D0 */
#define MAX_REGISTERS 125u /* [AP] 6.3, 6.4: quantity 1..0x7D */

int rtu_image_check(const rtu_image *img)
{
    unsigned t;
    if (img == NULL)
        return RTU_EINVAL;
    for (t = 0; t < RTU_IMAGE_TABLES; t++) {
        const rtu_image_range *r = img->ranges[t];
        uint32_t i, n = img->nranges[t];
        uint32_t next = 0; /* the first address the next range may start at */
        if (n > 0 && r == NULL)
            return RTU_EINVAL;
        for (i = 0; i < n; i++) {
            if (r[i].count == 0 || r[i].start >= ADDRESSES || r[i].count > ADDRESSES - r[i].start)
                return RTU_EINVAL;
            if (r[i].values == NULL ||
                (r[i].flags != RTU_IMAGE_PLAIN && r[i].flags != RTU_IMAGE_HELD))
                return RTU_EINVAL;
            if (i > 0 && r[i].start < next)
                return RTU_EINVAL; /* before the end of the previous range */
            next = r[i].start + r[i].count;
        }
    }
    return RTU_OK;
}

/* The index of the last range of r[0..n) that starts at or before `address`
 * (binary search on the sorted starts); n when there is none. */
static uint32_t find_range(const rtu_image_range *r, uint32_t n, uint32_t address)
{
    uint32_t lo = 0, hi = n; /* the answer + 1 lies in [lo, hi] */
    while (lo < hi) {
        const uint32_t mid = lo + (hi - lo) / 2;
        if (r[mid].start <= address)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo == 0 ? n : lo - 1;
}

int rtu_image_answer(const rtu_image *img, const uint8_t *pdu, size_t len, uint8_t *out, size_t cap,
                     size_t *out_len)
{
    unsigned fc;
    uint32_t address, quantity, end, pos, i, n, k;
    const rtu_image_range *r;
    int bits;
    if (img == NULL || pdu == NULL || out == NULL || out_len == NULL || cap < RTU_IMAGE_MAX_ANSWER)
        return RTU_EINVAL;
    /* [AP] 6.1-6.4: function, starting address, quantity; 5 bytes */
    if (len != 5)
        return RTU_IMAGE_DEFER;
    fc = pdu[0];
    if (fc < 1 || fc > 4)
        return RTU_IMAGE_DEFER;
    bits = fc <= 2;
    address = (uint32_t)pdu[1] << 8 | pdu[2];
    quantity = (uint32_t)pdu[3] << 8 | pdu[4];
    if (quantity < 1 || quantity > (bits ? MAX_BITS : MAX_REGISTERS))
        return RTU_IMAGE_DEFER; /* Python answers exception 03 */
    end = address + quantity;
    if (end > ADDRESSES)
        return RTU_IMAGE_DEFER; /* Python answers exception 02 */
    /* FC 01 -> coils (0), 02 -> discrete inputs (1), 03 -> holding (2), 04 -> input (3) */
    r = img->ranges[fc - 1];
    n = img->nranges[fc - 1];
    if (n == 0 || r == NULL)
        return RTU_IMAGE_DEFER;
    i = find_range(r, n, address);
    if (i == n)
        return RTU_IMAGE_DEFER; /* before the first range */

    out[0] = (uint8_t)fc;
    if (bits) {
        /* [AP] 6.1/6.2: N = ceil(quantity / 8) bytes, LSB first, high bits 0 */
        const uint32_t nbytes = (quantity + 7) / 8;
        out[1] = (uint8_t)nbytes;
        memset(out + 2, 0, nbytes);
    } else {
        out[1] = (uint8_t)(2 * quantity); /* [AP] 6.3/6.4: 2 x N bytes */
    }
    /* Walk the ranges from the one holding `address`: each must be plain and
     * follow the previous with no gap until `end` (a read spans adjacent ranges). */
    k = 0; /* the index of the value being answered, 0 .. quantity - 1 */
    pos = address;
    while (pos < end) {
        uint32_t stop, j;
        if (i >= n || r[i].start > pos || pos - r[i].start >= r[i].count)
            return RTU_IMAGE_DEFER; /* an address outside every range: exception 02 */
        if (r[i].flags != RTU_IMAGE_PLAIN)
            return RTU_IMAGE_DEFER; /* held: its on_read runs in Python */
        stop = r[i].count - (pos - r[i].start) < end - pos ? r[i].start + r[i].count : end;
        for (j = pos - r[i].start; pos < stop; pos++, j++, k++) {
            const uint16_t v = r[i].values[j];
            if (bits) {
                if (v != 0)
                    out[2 + k / 8] |= (uint8_t)(1u << (k % 8));
            } else {
                out[2 + 2 * k] = (uint8_t)(v >> 8); /* big-endian */
                out[3 + 2 * k] = (uint8_t)(v & 0xFF);
            }
        }
        i++;
    }
    *out_len = 2 + (size_t)out[1];
    return RTU_OK;
}
