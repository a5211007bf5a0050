/* libFuzzer harness: every CRC path (csrc/rtu_crc.c) against the Appendix B
 * byte loop ([SL] 6.2.2, Appendix B), at the input's length and at a fuzzed
 * alignment, split in two at a fuzzed point (the CRC is incremental), from a
 * fuzzed seed; and the LRC ([SL] 6.2.1) against its definition.
 *
 * fuzz/Makefile builds this harness with the folding thresholds lowered
 * (RTU_CLMUL_MIN=16, RTU_VCLMUL_MIN=2, dispatch from 1 / 2 bytes), so that the
 * PCLMULQDQ / VPCLMULQDQ code runs at short lengths too.
 *
 * Input: seed (2 bytes), split point (2), alignment (1), then the message. */
#include "fuzz_common.h"

int LLVMFuzzerTestOneInput(const uint8_t *input, size_t size)
{
    fuzz_in in = {input, size};
    const uint16_t seed = fuzz_u16(&in);
    const size_t split_raw = fuzz_u16(&in);
    const size_t align = fuzz_u8(&in) % 64;
    const size_t len = in.n;
    const size_t split = len ? split_raw % (len + 1) : 0;
    /* a heap block that ends exactly at the message's end */
    uint8_t *block = malloc(align + len + (align + len == 0));
    uint8_t *msg = block + align;
    memcpy(msg, in.p, len);
    const uint16_t want = rtu_crc16_bytewise(len ? msg : NULL, len, seed);
    uint8_t lrc = 0;
    for (size_t i = 0; i < len; i++) {
        lrc = (uint8_t)(lrc + msg[i]);
    }
    if (rtu_lrc(len ? msg : NULL, len) != (uint8_t)(0u - lrc)) {
        FUZZ_FAIL("LRC differs from the two's complement of the byte sum");
    }
    if (rtu_crc16(len ? msg : NULL, len, seed) != want) {
        FUZZ_FAIL("rtu_crc16 differs from the byte loop at %zu bytes", len);
    }
    for (int path = 0; path < RTU_CRC_NPATHS; path++) {
        uint16_t whole = 0, first = 0, both = 0;
        const int st = rtu_crc16_path(path, len ? msg : NULL, len, seed, &whole);
        if (!rtu_crc16_path_available(path)) {
            if (st != RTU_EUNSUPPORTED) {
                FUZZ_FAIL("path %d unavailable but status %d", path, st);
            }
            continue;
        }
        if (st != RTU_OK || whole != want) {
            FUZZ_FAIL("path %d: %04x, want %04x (%zu bytes, align %zu)", path, whole, want, len,
                      align);
        }
        (void)rtu_crc16_path(path, split ? msg : NULL, split, seed, &first);
        (void)rtu_crc16_path(path, len - split ? msg + split : NULL, len - split, first, &both);
        if (both != want) {
            FUZZ_FAIL("path %d split at %zu: %04x, want %04x", path, split, both, want);
        }
    }
    uint16_t out;
    if (rtu_crc16_path(RTU_CRC_NPATHS, msg, len, seed, &out) != RTU_EINVAL ||
        rtu_crc16_path(-1, msg, len, seed, &out) != RTU_EINVAL ||
        rtu_crc16_path(RTU_CRC_BYTEWISE, msg, len, seed, NULL) != RTU_EINVAL ||
        (len > 0 && rtu_crc16_path(RTU_CRC_BYTEWISE, NULL, len, seed, &out) != RTU_EINVAL)) {
        FUZZ_FAIL("rtu_crc16_path accepted a bad argument");
    }
    free(block);
    return 0;
}
