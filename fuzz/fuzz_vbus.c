/* libFuzzer harness for the virtual bus's sans-I/O schedule (csrc/rtu_vbus.c).
 *
 * Input: byte 0 picks the drop count (1..4), bytes 1-2 the character time and the
 * lead; then a sequence of operations, each an opcode byte and its operands: transmit
 * (drop, length, bytes, time), service (time), echo, batch, unplug-after, cut,
 * clear-hold, plug/unplug, written (any count, any heard flag), with hostile times
 * (int64 extremes, backwards) and drop indexes past the end.  The schedule never
 * sees time go backwards from a well-behaved caller, but it must not misbehave when
 * it does.
 *
 * Invariants after every operation: queues, held and output bytes within their
 * bounds (RTU_VBUS_QUEUE, RTU_VBUS_OUT), held bytes iff a release time; characters are conserved:
 * every byte queued is on the wire, still queued, or dropped by an unplug;
 * collisions <= collided <= wire_bytes; after a successful service at `now`, the
 * next deadline is later than `now` (nothing due is left behind); a refused call
 * changes nothing it reports. */
#include "rtu_vbus.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fuzz_common.h"

#define NDROPS 4

static rtu_vbus_drop drops[NDROPS];

static uint64_t queued_total(const rtu_vbus *s)
{
    uint64_t n = 0;
    for (uint32_t i = 0; i < s->ndrops; i++)
        n += s->drops[i].q_len;
    return n;
}

static void check(const rtu_vbus *s, uint64_t in, uint64_t dropped)
{
    for (uint32_t i = 0; i < s->ndrops; i++) {
        const rtu_vbus_drop *d = &s->drops[i];
        if (d->q_len > RTU_VBUS_QUEUE)
            FUZZ_FAIL("drop %u: queue length %u", i, d->q_len);
        if (d->out_len > RTU_VBUS_OUT)
            FUZZ_FAIL("drop %u: output length %u", i, d->out_len);
        /* a batch shrunk while bytes are held releases at the next byte: the bound
         * is the buffer's */
        if (d->hold_len >= RTU_VBUS_OUT)
            FUZZ_FAIL("drop %u: %u bytes held", i, d->hold_len);
        if ((d->hold_len == 0) != (d->hold_deadline == RTU_VBUS_NO_TIME))
            FUZZ_FAIL("drop %u: held bytes without a deadline or the reverse", i);
    }
    if (s->wire_bytes + queued_total(s) + dropped != in)
        FUZZ_FAIL("characters not conserved: %llu on the wire + %llu queued + %llu dropped != %llu",
                  (unsigned long long)s->wire_bytes, (unsigned long long)queued_total(s),
                  (unsigned long long)dropped, (unsigned long long)in);
    if (s->collisions > s->collided || s->collided > s->wire_bytes)
        FUZZ_FAIL("collision counters out of order");
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static const int64_t chars[4] = {86806, 1145833, 1, RTU_VBUS_MAX_CHAR_NS};
    fuzz_in in = {data, size};
    rtu_vbus s;
    uint32_t n = 1 + fuzz_u8(&in) % NDROPS;
    int64_t c = chars[fuzz_u8(&in) % 4];
    int64_t lead = (fuzz_u8(&in) % 3) * 20000;
    int64_t now = 0;
    uint64_t queued = 0, dropped = 0;
    uint8_t buf[512];
    if (rtu_vbus_init(&s, drops, n, c, lead) != RTU_OK)
        FUZZ_FAIL("init refused a valid configuration");
    if (rtu_vbus_init(&s, drops, 0, c, lead) != RTU_EINVAL ||
        rtu_vbus_init(&s, drops, n, 0, lead) != RTU_EINVAL)
        FUZZ_FAIL("init accepted a bad configuration");
    rtu_vbus_init(&s, drops, n, c, lead);
    for (uint32_t i = 0; i < n; i++)
        rtu_vbus_plug(&s, i);
    while (in.n > 0) {
        uint8_t op = fuzz_u8(&in);
        uint32_t drop = fuzz_u8(&in) % (NDROPS + 2); /* past the end too */
        switch (op % 10) {
        case 0:
        case 1: { /* transmit */
            size_t len = fuzz_u8(&in) % 80, k;
            int64_t t = op & 0x80 ? fuzz_time(&in, now) : now + (int64_t)fuzz_u8(&in) * 1000;
            size_t before = drop < n ? s.drops[drop].q_len : 0;
            int rc;
            if (op & 0x40)
                len *= 60; /* up to 4740 bytes: past the queue's bound */
            if (len > sizeof buf && !(op & 0x40))
                len = sizeof buf;
            for (k = 0; k < len && k < sizeof buf; k++)
                buf[k] = fuzz_u8(&in);
            if (len > sizeof buf) { /* a long write: the buffer repeated */
                static uint8_t big[RTU_VBUS_QUEUE + 1024];
                for (k = 0; k < len; k++)
                    big[k] = buf[k % sizeof buf];
                rc = rtu_vbus_transmit(&s, drop, big, len, t);
            } else {
                rc = rtu_vbus_transmit(&s, drop, buf, len, t);
            }
            if (drop < n) {
                size_t after = s.drops[drop].q_len;
                if (rc != RTU_OK && after != before)
                    FUZZ_FAIL("a refused transmit queued %zu bytes", after - before);
                if (rc == RTU_ENOSPC && len <= RTU_VBUS_QUEUE - before)
                    FUZZ_FAIL("RTU_ENOSPC with room");
                queued += after - before;
            } else if (rc != RTU_EINVAL) {
                FUZZ_FAIL("transmit to drop %u of %u accepted", drop, n);
            }
            if (rc == RTU_OK && t >= now && t < ((int64_t)1 << 61))
                now = t;
            break;
        }
        case 2: { /* service */
            int64_t t = op & 0x80 ? fuzz_time(&in, now) : now + (int64_t)fuzz_u16(&in) * 100;
            int rc = rtu_vbus_service(&s, t);
            if (rc >= 0) {
                int64_t dl = rtu_vbus_deadline(&s);
                int due = 0;
                while (rtu_vbus_take_due(&s) >= 0)
                    due++;
                if (due != rc)
                    FUZZ_FAIL("service said %d drops due, take_due gave %d", rc, due);
                if (dl != RTU_VBUS_NO_TIME && dl <= t)
                    FUZZ_FAIL("deadline %lld not after service at %lld", (long long)dl,
                              (long long)t);
                if (t > now)
                    now = t;
            }
            break;
        }
        case 3:
            rtu_vbus_set_echo(&s, drop, op & 1);
            break;
        case 4:
            rtu_vbus_set_batch(&s, drop, (int64_t)fuzz_u16(&in) * (op & 0x80 ? 100000 : 100),
                               op & 0x40 ? (uint32_t)fuzz_u16(&in) : 1 + fuzz_u8(&in) % 64);
            break;
        case 5:
            rtu_vbus_set_unplug_after(&s, drop, (int64_t)fuzz_u8(&in) - 8);
            break;
        case 6:
            rtu_vbus_cut(&s, drop, op & 0x80 ? fuzz_time(&in, now) : now + fuzz_u16(&in));
            break;
        case 7:
            rtu_vbus_clear_hold(&s, drop);
            break;
        case 8:
            if (drop < n && !(op & 0x80)) {
                dropped += s.drops[drop].q_len;
                rtu_vbus_unplug(&s, drop);
            } else {
                rtu_vbus_plug(&s, drop);
            }
            break;
        default: {
            size_t want = fuzz_u16(&in) % (RTU_VBUS_OUT + 2);
            int heard = (int)(fuzz_u8(&in) % 3) - 1;
            int rc = rtu_vbus_written(&s, drop, want, heard);
            if (drop < n && rc == RTU_OK && s.drops[drop].out_len != 0)
                FUZZ_FAIL("written left output behind");
            break;
        }
        }
        check(&s, queued, dropped);
        rtu_vbus_busy(&s);
        (void)rtu_vbus_space(&s, drop);
    }
    return 0;
}
