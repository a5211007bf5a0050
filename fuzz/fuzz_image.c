/* libFuzzer harness for the image of a DataStore (csrc/rtu_image.c): plain reads
 * answered from the caller's ranges.
 *
 * [AP] MODBUS Application Protocol Specification V1.1b3, 6.1-6.4.
 *
 * Input: byte 0 flags (bit 0: break the image on purpose: a range unsorted,
 * overlapping, of count 0, past 65535, with unknown flags or NULL values; bits
 * 1..3: how many PDUs follow, 1..8), then for each of the four tables a count
 * of ranges (0..4) and each range (a gap after the previous one, a count, held
 * or plain, a seed of its values), then the PDUs (a length mode, then the
 * function, address and quantity, drawn near the ranges' edges and the limits).
 *
 * Every array is allocated at its exact size (ranges, values, the PDU, the
 * answer's 253 bytes), so ASan sees any read or write past one.  Checked:
 * rtu_image_check agrees with a checker of this file; on a checked image,
 * rtu_image_answer answers exactly when every condition of rtu_image.h holds
 * (PDU of 5 bytes, FC 1..4, quantity 1..2000 or 1..125, address + quantity <=
 * 65536, every address in a plain range of the function's table), and then its
 * bytes are those of a per-address reference loop here; else it defers
 * (RTU_IMAGE_DEFER), never anything else.  A violated invariant aborts. */
#include "fuzz_common.h"
#include "rtu_image.h"

#define MAX_RANGES 4

/* An independent look at one table: sorted, not overlapping, in bounds. */
static int table_ok(const rtu_image_range *r, uint32_t n)
{
    uint32_t i;
    if (n > 0 && r == NULL)
        return 0;
    for (i = 0; i < n; i++) {
        uint64_t end = (uint64_t)r[i].start + r[i].count;
        if (r[i].count == 0 || r[i].start > 65535 || end > 65536 || r[i].values == NULL)
            return 0;
        if (r[i].flags > 1)
            return 0;
        if (i > 0 && r[i].start < (uint64_t)r[i - 1].start + r[i - 1].count)
            return 0;
    }
    return 1;
}

/* The value at `a` of table r[0..n): 1 and *v, or 0 when no range holds it; *held
 * when the range is held.  A linear search, one address at a time. */
static int value_at(const rtu_image_range *r, uint32_t n, uint32_t a, uint16_t *v, int *held)
{
    uint32_t i;
    for (i = 0; i < n; i++) {
        if (a >= r[i].start && a - r[i].start < r[i].count) {
            *v = r[i].values[a - r[i].start];
            *held = r[i].flags != RTU_IMAGE_PLAIN;
            return 1;
        }
    }
    return 0;
}

/* The reference answer: its length, 0 when the image must defer. */
static size_t reference(const rtu_image *img, const uint8_t *pdu, size_t len, uint8_t *out)
{
    unsigned fc, address, quantity, k;
    if (len != 5 || pdu[0] < 1 || pdu[0] > 4)
        return 0;
    fc = pdu[0];
    address = (unsigned)pdu[1] << 8 | pdu[2];
    quantity = (unsigned)pdu[3] << 8 | pdu[4];
    if (quantity < 1 || quantity > (fc <= 2 ? 2000u : 125u) || address + quantity > 65536)
        return 0;
    memset(out, 0, 253);
    out[0] = (uint8_t)fc;
    out[1] = (uint8_t)(fc <= 2 ? (quantity + 7) / 8 : 2 * quantity);
    for (k = 0; k < quantity; k++) {
        uint16_t v = 0;
        int held = 0;
        if (!value_at(img->ranges[fc - 1], img->nranges[fc - 1], address + k, &v, &held) || held)
            return 0;
        if (fc <= 2) {
            if (v != 0)
                out[2 + k / 8] = (uint8_t)(out[2 + k / 8] | 1u << (k % 8));
        } else {
            out[2 + 2 * k] = (uint8_t)(v >> 8);
            out[3 + 2 * k] = (uint8_t)v;
        }
    }
    return 2 + (size_t)out[1];
}

static uint32_t lcg(uint32_t *x)
{
    *x = *x * 1103515245u + 12345u;
    return *x >> 8;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fuzz_in in = {data, size};
    rtu_image img;
    rtu_image_range *arrays[RTU_IMAGE_TABLES] = {NULL, NULL, NULL, NULL};
    uint16_t *values[RTU_IMAGE_TABLES][MAX_RANGES];
    const uint8_t flags = fuzz_u8(&in);
    unsigned t, i, npdus;
    int ok, want;
    memset(&img, 0, sizeof img);
    memset(values, 0, sizeof values);
    for (t = 0; t < RTU_IMAGE_TABLES; t++) {
        const unsigned n = fuzz_u8(&in) % (MAX_RANGES + 1);
        uint32_t pos = 0;
        if (n == 0)
            continue;
        arrays[t] = malloc(sizeof(rtu_image_range) * n);
        if (arrays[t] == NULL)
            FUZZ_FAIL("malloc");
        for (i = 0; i < n; i++) {
            rtu_image_range *r = &arrays[t][i];
            const uint8_t how = fuzz_u8(&in);
            uint32_t count, j, seed = fuzz_u8(&in);
            switch (how & 3) { /* the gap before it */
            case 0:
                break; /* adjacent */
            case 1:
                pos += 1 + (how >> 2) % 8;
                break;
            case 2:
                pos += fuzz_u16(&in);
                break;
            default:
                pos = 65536 - 1 - (how >> 2) % 4000; /* near the end */
            }
            switch ((how >> 4) & 3) { /* its count */
            case 0:
                count = 1 + fuzz_u8(&in) % 16;
                break;
            case 1:
                count = 1 + fuzz_u16(&in) % 300;
                break;
            case 2:
                count = 1 + fuzz_u16(&in) % 2100;
                break;
            default:
                count = 65536 - (pos & 0xFFFF); /* to the end */
            }
            if (pos > 65535)
                pos = 65535;
            if (count > 65536 - pos)
                count = 65536 - pos;
            r->start = pos;
            r->count = count;
            r->flags = (how >> 6) == 3 ? RTU_IMAGE_HELD : RTU_IMAGE_PLAIN;
            values[t][i] = malloc(sizeof(uint16_t) * count);
            if (values[t][i] == NULL)
                FUZZ_FAIL("malloc");
            for (j = 0; j < count; j++) {
                const uint32_t v = lcg(&seed);
                values[t][i][j] = (uint16_t)(t < 2 ? ((v & 7) == 0 ? v : v & 1) : v);
            }
            r->values = values[t][i];
            pos += count;
        }
        img.ranges[t] = arrays[t];
        img.nranges[t] = n;
    }
    if (flags & 1) { /* break one range of the first table that has any */
        const uint8_t how = fuzz_u8(&in);
        for (t = 0; t < RTU_IMAGE_TABLES; t++) {
            if (img.nranges[t] > 0) {
                rtu_image_range *r = &arrays[t][how % img.nranges[t]];
                switch ((how >> 3) % 6) {
                case 0:
                    r->count = 0;
                    break;
                case 1:
                    r->start = r->start > 0 ? r->start - 1 : 65536;
                    break;
                case 2:
                    r->count = 65537 - (r->start & 0xFFFF); /* past 65535 */
                    break;
                case 3:
                    r->flags = 2 + (how >> 6);
                    break;
                case 4:
                    r->values = NULL;
                    break;
                default:
                    r->start = 70000;
                }
                break;
            }
        }
    }
    ok = rtu_image_check(&img);
    want = 1;
    for (t = 0; t < RTU_IMAGE_TABLES; t++)
        want = want && table_ok(img.ranges[t], img.nranges[t]);
    if ((ok == RTU_OK) != want || (ok != RTU_OK && ok != RTU_EINVAL))
        FUZZ_FAIL("rtu_image_check %d, the reference says %s", ok, want ? "valid" : "invalid");

    npdus = 1 + ((flags >> 1) & 7);
    for (i = 0; ok == RTU_OK && i < npdus; i++) {
        const uint8_t mode = fuzz_u8(&in);
        size_t len = (mode & 7) == 7 ? fuzz_u8(&in) % 9 : 5;
        uint8_t *pdu = malloc(len > 0 ? len : 1);
        uint8_t *out = malloc(RTU_IMAGE_MAX_ANSWER);
        uint8_t ref[253];
        size_t out_len = 0, ref_len;
        unsigned fc, address, quantity, limit;
        int rc;
        if (pdu == NULL || out == NULL)
            FUZZ_FAIL("malloc");
        fc = ((mode >> 3) & 7) < 6 ? 1 + ((mode >> 3) & 3) : fuzz_u8(&in);
        limit = fc <= 2 ? 2000 : 125;
        address = fuzz_u16(&in);
        {
            const unsigned table = (fc - 1) & 3;
            const uint8_t near = fuzz_u8(&in);
            if (img.nranges[table] > 0 && (near & 1)) { /* at a range's edge */
                const rtu_image_range *r = &img.ranges[table][(near >> 1) % img.nranges[table]];
                address = (near & 2) ? r->start + r->count - 1 : r->start;
                address = (address + (near >> 4) - 8) & 0xFFFF;
            }
        }
        switch (mode >> 6) {
        case 0:
            quantity = 1 + fuzz_u8(&in) % 16;
            break;
        case 1: {
            static const unsigned edge[6] = {0, 1, 2000, 2001, 125, 126};
            quantity = edge[fuzz_u8(&in) % 6];
            break;
        }
        case 2:
            quantity = 1 + fuzz_u16(&in) % limit;
            break;
        default:
            quantity = fuzz_u16(&in);
        }
        {
            uint8_t full[9];
            full[0] = (uint8_t)fc;
            full[1] = (uint8_t)(address >> 8);
            full[2] = (uint8_t)address;
            full[3] = (uint8_t)(quantity >> 8);
            full[4] = (uint8_t)quantity;
            full[5] = full[6] = full[7] = full[8] = fuzz_u8(&in);
            memcpy(pdu, full, len);
        }
        rc = rtu_image_answer(&img, pdu, len, out, RTU_IMAGE_MAX_ANSWER, &out_len);
        ref_len = reference(&img, pdu, len, ref);
        if (ref_len > 0) {
            if (rc != RTU_OK || out_len != ref_len || memcmp(out, ref, ref_len) != 0)
                FUZZ_FAIL("fc %u address %u quantity %u len %zu: rc %d, %zu bytes, the "
                          "reference %zu",
                          fc, address, quantity, len, rc, out_len, ref_len);
        } else if (rc != RTU_IMAGE_DEFER) {
            FUZZ_FAIL("fc %u address %u quantity %u len %zu: rc %d where it must defer", fc,
                      address, quantity, len, rc);
        }
        if (rtu_image_answer(&img, pdu, len, out, RTU_IMAGE_MAX_ANSWER - 1, &out_len) != RTU_EINVAL)
            FUZZ_FAIL("a capacity below 253 accepted");
        free(pdu);
        free(out);
    }
    for (t = 0; t < RTU_IMAGE_TABLES; t++) {
        for (i = 0; i < MAX_RANGES; i++)
            free(values[t][i]);
        free(arrays[t]);
    }
    return 0;
}
