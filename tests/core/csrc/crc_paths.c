/* Every CRC path against the Appendix B byte loop ([SL] 6.2.2, Appendix B), at
 * every length 0..1100 and 8 alignments, each message in a heap block of its
 * exact size so that AddressSanitizer sees any read past either end.
 *
 * Built by tests/core/test_crc_paths.py twice: with the production thresholds and
 * with -DRTU_CLMUL_MIN=16 -DRTU_VCLMUL_MIN=2 -DRTU_DISPATCH_CLMUL=1
 * -DRTU_DISPATCH_VCLMUL=2, so that the folding code runs at every length it
 * accepts, not only from 48 / 64 bytes on.
 *
 * Output: one line per path, "<path> ran|unavailable", then "ok <checks>";
 * exit status 1 and "MISMATCH ..." on the first disagreement. */
#include "rtu.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_LEN 1100
#define ALIGNS 8

static const char *const names[RTU_CRC_NPATHS] = {"bytewise", "slice8", "clmul", "vclmul"};

static uint32_t rng_state = 0x12345678u;

static uint8_t rng_byte(void)
{
    rng_state = rng_state * 1103515245u + 12345u;
    return (uint8_t)(rng_state >> 16);
}

int main(void)
{
    static uint8_t pattern[MAX_LEN + ALIGNS];
    const uint16_t seeds[3] = {RTU_CRC_INIT, 0x0000, 0xA5C3};
    unsigned long checks = 0;
    for (size_t i = 0; i < sizeof pattern; i++) {
        pattern[i] = rng_byte();
    }
    for (int path = 0; path < RTU_CRC_NPATHS; path++) {
        printf("%s %s\n", names[path], rtu_crc16_path_available(path) ? "ran" : "unavailable");
    }
    /* NULL with length 0 is allowed (rtu_crc.h) and returns the seed. */
    for (int path = 0; path < RTU_CRC_NPATHS; path++) {
        uint16_t out = 0;
        const int st = rtu_crc16_path(path, NULL, 0, 0xBEEF, &out);
        if (rtu_crc16_path_available(path) && (st != RTU_OK || out != 0xBEEF)) {
            printf("MISMATCH %s NULL/0: status %d crc %04x\n", names[path], st, out);
            return 1;
        }
    }
    if (rtu_crc16(NULL, 0, 0xBEEF) != 0xBEEF) {
        printf("MISMATCH rtu_crc16 NULL/0\n");
        return 1;
    }
    for (size_t len = 0; len <= MAX_LEN; len++) {
        for (size_t align = 0; align < ALIGNS; align++) {
            /* a block that ends exactly where the message ends */
            uint8_t *exact = malloc(align + len > 0 ? align + len : 1);
            if (exact == NULL) {
                printf("MISMATCH out of memory\n");
                return 1;
            }
            uint8_t *msg = exact + align;
            memcpy(msg, pattern + align, len);
            for (int s = 0; s < 3; s++) {
                const uint16_t want = rtu_crc16_bytewise(msg, len, seeds[s]);
                for (int path = 0; path < RTU_CRC_NPATHS; path++) {
                    uint16_t got = 0;
                    const int st = rtu_crc16_path(path, msg, len, seeds[s], &got);
                    if (st == RTU_EUNSUPPORTED && !rtu_crc16_path_available(path)) {
                        continue;
                    }
                    checks++;
                    if (st != RTU_OK || got != want) {
                        printf("MISMATCH %s len %zu align %zu seed %04x: %04x, want %04x\n",
                               names[path], len, align, seeds[s], got, want);
                        return 1;
                    }
                }
                checks++;
                if (rtu_crc16(msg, len, seeds[s]) != want) {
                    printf("MISMATCH dispatch len %zu align %zu\n", len, align);
                    return 1;
                }
            }
            free(exact);
        }
    }
    printf("ok %lu\n", checks);
    return 0;
}
