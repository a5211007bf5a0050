/* libFuzzer harness for a Modbus TCP client's transaction: the scan of its receive
 * buffer (csrc/rtu_tcp.c) and the transaction on a socket (csrc/rtu_tcp_io.c).
 *
 * Input: byte 0 the transaction id awaited (0..255), byte 1 the unit, byte 2 the
 * function code of the request (1..127), byte 3 seeds the scan's piece sizes; the
 * rest is what the server sends back ([TCP] MODBUS Messaging on TCP/IP
 * Implementation Guide V1.0b, 3.1.3).
 *
 * 1. The scan: the bytes scanned in growing prefixes (as reads bring them) give
 *    the same result as one scan of all of them; every resolved ADU has a valid
 *    header and its length; the answer has the awaited transaction id and no
 *    earlier ADU has; late counts every other resolved ADU; an error stops at
 *    `used` and is what rtu_mbap_inspect says there.
 * 2. The transaction: the bytes are written into one end of a socket pair and
 *    that end is shut down; rtu_tcp_xfer_run on the other end (deadline 0: what
 *    is there) must end as the scan says: the answer judged by its unit and
 *    function, a bad header, or the end of file; the request it sent is the MBAP
 *    ADU of the PDU; the buffer is never overrun (a flood of late ADUs is
 *    compacted).  A violated invariant aborts (libFuzzer records a crash). */
#include "fuzz_common.h"
#include "rtu_tcp.h"

#include <sys/socket.h>
#include <unistd.h>

static unsigned be16(const uint8_t *p) { return ((unsigned)p[0] << 8) | p[1]; }

static void check_scan(const uint8_t *data, size_t n, unsigned tid, const rtu_tcp_scan_result *s)
{
    size_t pos = 0, late = 0, late_after = 0;
    int answered = 0;
    if (s->used > n || s->late_after > s->late)
        FUZZ_FAIL("used %zu of %zu, late_after %u of %u", s->used, n, s->late_after, s->late);
    while (pos < s->used) {
        size_t length = 0;
        int error = 0;
        if (rtu_mbap_inspect(data + pos, s->used - pos, &length, &error) != RTU_MBAP_COMPLETE)
            FUZZ_FAIL("a resolved ADU at %zu is not whole", pos);
        if (s->ans_len != 0 && pos == s->ans_off) {
            if (be16(data + pos) != tid || length != s->ans_len || answered)
                FUZZ_FAIL("the answer at %zu is not transaction %u's", pos, tid);
            answered = 1;
        } else {
            if (!answered && be16(data + pos) == tid)
                FUZZ_FAIL("an answer at %zu was taken for late", pos);
            late++;
            late_after += (size_t)answered;
        }
        pos += length;
    }
    if (pos != s->used || late != s->late || late_after != s->late_after ||
        answered != (s->ans_len != 0))
        FUZZ_FAIL("the scan's counts differ from its ADUs");
    if (s->used < n) {
        size_t length = 0;
        int error = 0;
        int r = rtu_mbap_inspect(data + s->used, n - s->used, &length, &error);
        if ((r == RTU_MBAP_INVALID) != (s->error != 0) ||
            (r == RTU_MBAP_INVALID && error != s->error))
            FUZZ_FAIL("the error at %zu differs from rtu_mbap_inspect", s->used);
        if (r == RTU_MBAP_COMPLETE)
            FUZZ_FAIL("the scan stopped before a whole ADU at %zu", s->used);
    } else if (s->error != 0) {
        FUZZ_FAIL("an error past the end");
    }
}

static void scan_in_pieces(const uint8_t *data, size_t n, unsigned tid, uint32_t seed)
{
    rtu_tcp_scan_result whole, pieces;
    size_t have = 0;
    memset(&whole, 0, sizeof whole);
    memset(&pieces, 0, sizeof pieces);
    if (rtu_tcp_scan(data, n, tid, &whole) != RTU_OK)
        FUZZ_FAIL("scan");
    check_scan(data, n, tid, &whole);
    while (have < n) {
        seed = seed * 1103515245u + 12345u;
        have += 1 + (seed >> 16) % 64;
        if (have > n)
            have = n;
        if (rtu_tcp_scan(data, have, tid, &pieces) != RTU_OK)
            FUZZ_FAIL("scan of a prefix");
    }
    if (n > 0 && memcmp(&whole, &pieces, sizeof whole) != 0)
        FUZZ_FAIL("the scan in pieces differs from one scan");
}

static uint8_t rx[RTU_TCP_MIN_CAP * 2];

static void transact(const uint8_t *data, size_t n, unsigned tid, unsigned unit, unsigned fc)
{
    int sv[2];
    uint8_t pdu[5] = {0, 0, 0, 0, 2};
    rtu_tcp_xfer x;
    rtu_tcp_scan_result s;
    uint8_t got[RTU_TCP_REQ_CAP];
    ssize_t sent;
    pdu[0] = (uint8_t)fc;
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, sv) != 0)
        return; /* out of descriptors: nothing to judge */
    if (n > 0 && write(sv[1], data, n) != (ssize_t)n) {
        close(sv[0]);
        close(sv[1]);
        return; /* more than the socket buffer: not this harness's question */
    }
    shutdown(sv[1], SHUT_WR);
    memset(&x, 0, sizeof x);
    x.fd = sv[0];
    x.send = 1;
    x.awaited = 1;
    x.tid = tid;
    x.unit = unit;
    x.pdu = pdu;
    x.pdu_len = sizeof pdu;
    x.timeout_ns = 0;
    x.buf = rx;
    x.cap = sizeof rx;
    if (rtu_tcp_xfer_run(&x) != RTU_OK)
        FUZZ_FAIL("xfer run");
    sent = read(sv[1], got, sizeof got);
    if (sent != 7 + (ssize_t)sizeof pdu || be16(got) != tid || be16(got + 2) != 0 ||
        be16(got + 4) != 1 + sizeof pdu || got[6] != unit || memcmp(got + 7, pdu, sizeof pdu) != 0)
        FUZZ_FAIL("the request sent is not the MBAP ADU of the PDU");
    if (x.n > x.cap || x.scan.used > x.n)
        FUZZ_FAIL("the buffer is overrun: n %zu, used %zu", x.n, x.scan.used);
    /* what the transaction saw is the tail of the stream (a compaction dropped
     * only whole late ADUs from its head) */
    memset(&s, 0, sizeof s);
    rtu_tcp_scan(data, n, tid, &s);
    switch (x.status) {
    case RTU_TCP_ANSWER:
    case RTU_TCP_EXCEPTION:
    case RTU_TCP_MISMATCH: {
        const uint8_t *a = x.buf + x.scan.ans_off;
        int mismatch = a[6] != unit || (a[7] & 0x7F) != fc;
        if (s.ans_len == 0 || x.scan.ans_len != s.ans_len ||
            memcmp(a, data + s.ans_off, s.ans_len) != 0)
            FUZZ_FAIL("an answer the scan of the stream does not find");
        if ((x.status == RTU_TCP_MISMATCH) != mismatch ||
            (!mismatch && (x.status == RTU_TCP_EXCEPTION) != ((a[7] & 0x80) != 0)))
            FUZZ_FAIL("status %d for unit %u fc %u", x.status, a[6], a[7]);
        break;
    }
    case RTU_TCP_BAD_HEADER:
        if (s.ans_len != 0 || s.error == 0 || x.scan.error != s.error)
            FUZZ_FAIL("a bad header the scan of the stream does not see");
        break;
    case RTU_TCP_CLOSED:
    case RTU_TCP_TIMEOUT: /* (the end of file may be seen late: timeout 0) */
        if (s.ans_len != 0 || s.error != 0)
            FUZZ_FAIL("status %d where the stream has an answer or an error", x.status);
        break;
    default:
        FUZZ_FAIL("status %d (err %d)", x.status, x.err);
    }
    close(sv[0]);
    close(sv[1]);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    unsigned tid, unit, fc;
    uint32_t seed;
    if (size < 4)
        return 0;
    tid = data[0];
    unit = data[1];
    fc = 1 + data[2] % 127;
    seed = data[3];
    data += 4;
    size -= 4;
    scan_in_pieces(data, size, tid, seed);
    transact(data, size, tid, unit, fc);
    return 0;
}
