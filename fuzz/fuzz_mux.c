/* libFuzzer harness for the mux (csrc/rtu_mux_io.c): many Modbus TCP client
 * connections behind one epoll descriptor.
 *
 * Input: byte 0 the transaction id (0..255), byte 1 the unit, byte 2 the
 * function code of the request (1..127), byte 3 flags (bit 0: the server shuts
 * its end after the bytes; bit 1: timeout 0; bit 2: a second transaction after
 * the first ends; bit 3, without bit 2: the request repeated, rtu_mux_repeat,
 * due only once the first ended), byte 4 seeds the sizes of the pieces the bytes come in; the
 * rest is what the server sends back ([TCP] MODBUS Messaging on TCP/IP
 * Implementation Guide V1.0b, 3.1.3).
 *
 * The bytes are written into one end of a socket pair in pieces, the mux serviced
 * after each; the other end is the mux's connection 0 (connection 1 stays idle).
 * Checked: the request sent is the MBAP ADU of the PDU; at most one record, for
 * connection 0, with the token given; an answer (ANSWER, EXCEPTION, MISMATCH)
 * is the one rtu_tcp_scan finds in the whole stream, judged by its unit and
 * function, with the late ADUs before it counted; BAD_HEADER is the scan's error
 * with no answer before it; CLOSED only once the server shut its end and with no
 * answer or error in the stream; TIMEOUT only with timeout 0 and no answer yet;
 * a repeat goes on after a plain answer only, and when due it sends the request
 * again with the next transaction id (or its connection has failed: a record);
 * nothing is read out of bounds (ASan) and the loop never blocks.  A violated
 * invariant aborts (libFuzzer records a crash). */
#include "fuzz_common.h"
#include "rtu_mux.h"
#include "rtu_tcp.h"

#include <sys/socket.h>
#include <unistd.h>

static unsigned be16(const uint8_t *p) { return ((unsigned)p[0] << 8) | p[1]; }

static void check(const rtu_mux_done *d, const uint8_t *data, size_t written, unsigned tid,
                  unsigned unit, unsigned fc, int shut, int zero)
{
    rtu_tcp_scan_result s;
    memset(&s, 0, sizeof s);
    rtu_tcp_scan(data, written, tid, &s);
    if (d->conn != 0 || d->token != 77 || d->tid != tid)
        FUZZ_FAIL("record of conn %u token %llu tid %u", d->conn, (unsigned long long)d->token,
                  d->tid);
    switch (d->status) {
    case RTU_TCP_ANSWER:
    case RTU_TCP_EXCEPTION:
    case RTU_TCP_MISMATCH: {
        const uint8_t *a = data + s.ans_off;
        int mismatch;
        if (s.ans_len == 0 || d->len != s.ans_len - 6 || memcmp(d->adu, a + 6, d->len) != 0)
            FUZZ_FAIL("an answer the scan of the stream does not find");
        mismatch = a[6] != unit || (a[7] & 0x7F) != fc;
        if ((d->status == RTU_TCP_MISMATCH) != mismatch ||
            (!mismatch && (d->status == RTU_TCP_EXCEPTION) != ((a[7] & 0x80) != 0)))
            FUZZ_FAIL("status %d for unit %u fc %u", d->status, a[6], a[7]);
        if (d->late != s.late - s.late_after)
            FUZZ_FAIL("late %u, the stream has %u before the answer", d->late,
                      s.late - s.late_after);
        break;
    }
    case RTU_TCP_BAD_HEADER:
        if (s.ans_len != 0 || s.error == 0 || d->err != s.error)
            FUZZ_FAIL("a bad header the scan of the stream does not see");
        break;
    case RTU_TCP_CLOSED:
        if (!shut || s.ans_len != 0 || s.error != 0)
            FUZZ_FAIL("closed where the stream goes on, or has an answer or an error");
        break;
    case RTU_TCP_TIMEOUT: /* (each service reads all that was written: a piece is
                             smaller than the room the buffer keeps) */
        if (!zero || s.ans_len != 0 || s.error != 0)
            FUZZ_FAIL("a timeout (after %lld ns) with an answer or an error read, or a 1 s "
                      "timeout",
                      (long long)(d->end - d->start));
        break;
    default:
        FUZZ_FAIL("status %d (err %d)", d->status, d->err);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    static rtu_mux *m;
    static rtu_mux_done out[4];
    unsigned tid, unit, fc, flags;
    uint32_t seed;
    uint8_t pdu[5] = {0, 0, 0, 0, 2};
    uint8_t got[RTU_TCP_REQ_CAP];
    int sv[2], idle[2], ended = 0;
    size_t written = 0;
    size_t n;
    if (size < 5)
        return 0;
    tid = data[0];
    unit = data[1];
    fc = 1 + data[2] % 127;
    flags = data[3];
    seed = data[4];
    data += 5;
    n = size - 5;
    pdu[0] = (uint8_t)fc;
    if (m == NULL && (m = malloc(rtu_mux_size(2))) == NULL)
        return 0;
    if (rtu_mux_init(m, 2) != RTU_OK)
        return 0; /* out of descriptors: nothing to judge */
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, sv) != 0) {
        rtu_mux_destroy(m);
        return 0;
    }
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, idle) != 0) {
        close(sv[0]);
        close(sv[1]);
        rtu_mux_destroy(m);
        return 0;
    }
    if (rtu_mux_attach(m, 0, sv[0]) != RTU_OK || rtu_mux_attach(m, 1, idle[0]) != RTU_OK)
        FUZZ_FAIL("attach");
    if (rtu_mux_attach(m, 0, sv[0]) != RTU_EINVAL)
        FUZZ_FAIL("attached twice");
    if (rtu_mux_submit(m, 0, 77, tid, unit, (const char *)pdu, sizeof pdu, 1,
                       (flags & 2) ? 0 : 1000000000) != RTU_OK)
        FUZZ_FAIL("submit");
    if (rtu_mux_submit(m, 0, 78, tid, unit, (const char *)pdu, sizeof pdu, 1, 0) != RTU_EINVAL)
        FUZZ_FAIL("a second transaction in flight");
    if ((flags & 8) && !(flags & 4) && rtu_mux_repeat(m, 0, INT64_MAX / 2, 1) != RTU_OK)
        FUZZ_FAIL("a repeat refused");
    if (read(sv[1], got, sizeof got) != 7 + (ssize_t)sizeof pdu || be16(got) != tid ||
        be16(got + 2) != 0 || be16(got + 4) != 1 + sizeof pdu || got[6] != unit ||
        memcmp(got + 7, pdu, sizeof pdu) != 0)
        FUZZ_FAIL("the request sent is not the MBAP ADU of the PDU");
    while (!ended) {
        size_t piece;
        int waiting;
        seed = seed * 1103515245u + 12345u;
        piece = 1 + (seed >> 16) % 96;
        if (piece > n - written)
            piece = n - written;
        if (piece > 0 && write(sv[1], data + written, piece) != (ssize_t)piece)
            break; /* more than the socket buffer: not this harness's question */
        written += piece;
        if (written == n && (flags & 1))
            shutdown(sv[1], SHUT_WR);
        waiting = rtu_mux_service(m);
        if (waiting < 0 || waiting > 1)
            FUZZ_FAIL("service: %d", waiting);
        if (waiting == 1) {
            if (rtu_mux_take(m, out, 4) != 1)
                FUZZ_FAIL("take");
            check(&out[0], data, written, tid, unit, fc, (flags & 1) && written == n,
                  (flags & 2) != 0);
            ended = 1;
        } else if (written == n) {
            break; /* no record: still in flight (a partial answer, or none) */
        }
    }
    if (rtu_mux_take(m, out, 4) != 0)
        FUZZ_FAIL("a record after the first");
    if (ended && (flags & 4)) { /* the next transaction: in flight or ended at once */
        int r =
            rtu_mux_submit(m, 0, 79, (tid + 1) & 0xFF, unit, (const char *)pdu, sizeof pdu, 1, 0);
        if (r != RTU_OK && r != 1)
            FUZZ_FAIL("the next transaction refused: %d", r);
        if (rtu_mux_service(m) < 0)
            FUZZ_FAIL("service");
    } else if (ended && (flags & 8)) { /* the repeat, due now */
        int plain = out[0].status == RTU_TCP_ANSWER && out[0].err == 0 && out[0].late == 0 &&
                    out[0].len > 0;
        if (out[0].flags != (plain ? RTU_MUX_REPEATING : 0u))
            FUZZ_FAIL("flags %u for status %d err %d late %u", out[0].flags, out[0].status,
                      out[0].err, out[0].late);
        if (plain) {
            int waiting;
            ssize_t r;
            if (rtu_mux_repeat(m, 0, 0, 1) != RTU_OK)
                FUZZ_FAIL("the repeat refused after a plain answer");
            waiting = rtu_mux_service(m);
            r = recv(sv[1], got, sizeof got, MSG_DONTWAIT);
            if (r > 0) {
                if (r != 7 + (ssize_t)sizeof pdu || be16(got) != tid + 1 || be16(got + 2) != 0 ||
                    got[6] != unit || memcmp(got + 7, pdu, sizeof pdu) != 0)
                    FUZZ_FAIL("the repeat's request is not the ADU with the next id");
            } else if (waiting != 1) {
                FUZZ_FAIL("a repeat due neither sent nor ended: %d", waiting);
            }
            if (rtu_mux_unrepeat(m, 0) != 1)
                FUZZ_FAIL("the repeat's transaction is neither in flight nor waiting");
        }
    }
    if (rtu_mux_detach(m, 0) != RTU_OK || rtu_mux_detach(m, 1) != RTU_OK)
        FUZZ_FAIL("detach");
    if (rtu_mux_take(m, out, 4) != 0 || rtu_mux_deadline(m) != INT64_MAX)
        FUZZ_FAIL("a record or a deadline left after the detach");
    rtu_mux_destroy(m);
    close(sv[0]);
    close(sv[1]);
    close(idle[0]);
    close(idle[1]);
    return 0;
}
