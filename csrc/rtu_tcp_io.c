/*
 * One Modbus TCP client transaction on a connected socket (declared in
 * rtu_tcp.h): the sync master's tcp:// transaction, run by pyrtu/tcp/client.py
 * through cffi with the GIL released for the call.
 *
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b.
 *
 * Steps:
 *   1. (send) the unresolved bytes of the last call (a partial ADU read before a
 *      timeout) move to the head of the buffer; the request ADU is built ([TCP]
 *      3.1.3: MBAP header, transaction id, protocol id 0, length = 1 + PDU, unit)
 *      and written whole (waiting for room until the deadline);
 *   2. (awaited) what was read before and each read since are scanned
 *      (rtu_tcp_scan): late answers are dropped, an invalid header ends it;
 *   3. until the answer is whole or the deadline: poll, then one recv of all
 *      there is (an answer split across segments is read as they come; two in
 *      one segment are both resolved);
 *   4. the answer's unit and function are checked against the request's ([TCP]
 *      3.1.3: the server copies the unit id; [AP] 7: an exception response is
 *      the function code + 0x80), the caller maps what differs to its error.
 * With x->io (MODBUS/TCP Security: the TLS of csrc/rtu_tls_io.c) the bytes go
 * through its send/recv and the waits are for what it wants (a TLS read may
 * need the socket writable); bytes it holds decrypted already are read without
 * a wait.
 * A signal (EINTR) ends the wait early (RTU_TCP_INTERRUPTED) so that Python runs
 * its handler; the caller then calls again with send = 0 to wait on.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu.h"
#include "rtu_clock.h"
#include "rtu_tcp.h"

#if defined(__unix__) || defined(__APPLE__)

#include <errno.h>
#include <poll.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/types.h>
#include <time.h>

#ifndef MSG_NOSIGNAL
#define MSG_NOSIGNAL 0 /* (macOS: SIGPIPE is ignored by Python anyway) */
#endif

static int failed(rtu_tcp_xfer *x, int stage, int err)
{
    x->status = err == EINTR ? RTU_TCP_INTERRUPTED : RTU_TCP_ERRNO;
    x->err = err;
    x->stage = stage;
    return RTU_OK;
}

/* Step 1: the request ADU on the socket; 0 sent, else the xfer is over. */
static int transmit(rtu_tcp_xfer *x)
{
    const size_t len = RTU_MBAP_HEADER_LEN + x->pdu_len;
    size_t done = 0;
    x->req[0] = (uint8_t)(x->tid >> 8); /* [TCP] 3.1.3: transaction id */
    x->req[1] = (uint8_t)(x->tid & 0xFF);
    x->req[2] = 0; /* protocol id 0: MODBUS */
    x->req[3] = 0;
    x->req[4] = (uint8_t)((x->pdu_len + 1) >> 8); /* length: unit id + PDU */
    x->req[5] = (uint8_t)((x->pdu_len + 1) & 0xFF);
    x->req[6] = (uint8_t)x->unit;
    memcpy(x->req + RTU_MBAP_HEADER_LEN, x->pdu, x->pdu_len);
    while (done < len) {
        short want = POLLOUT;
        ptrdiff_t w = x->io != NULL ? x->io->send(x->io, x->req + done, len - done, &want)
                                    : send(x->fd, x->req + done, len - done, MSG_NOSIGNAL);
        if (w > 0) {
            done += (size_t)w;
            continue;
        }
        if (w < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
            failed(x, RTU_TCP_STAGE_SEND, errno);
            return 1;
        }
        if (rtu_now_ns() >= x->deadline) {
            x->status = RTU_TCP_TIMEOUT; /* no room for the request in time */
            return 1;
        }
        if (rtu_wait_fd(x->fd, want, x->deadline) < 0 && errno != EINTR) {
            failed(x, RTU_TCP_STAGE_SEND, errno);
            return 1;
        }
    }
    return 0;
}

/* Step 4: the answer found (x->scan.ans_len > 0) judged against the request. */
static void judge(rtu_tcp_xfer *x)
{
    const uint8_t *adu = x->buf + x->scan.ans_off;
    const unsigned fc = x->req[RTU_MBAP_HEADER_LEN]; /* the request's function code */
    if (adu[6] != x->unit || (adu[7] & 0x7Fu) != fc)
        x->status = RTU_TCP_MISMATCH;
    else if ((adu[7] & 0x80u) != 0)
        x->status = RTU_TCP_EXCEPTION;
    else
        x->status = RTU_TCP_ANSWER;
}

/* Step 2 on the bytes there are: 1 the xfer is over (x->status set), 0 read on. */
static int scanned(rtu_tcp_xfer *x)
{
    rtu_tcp_scan(x->buf, x->n, x->tid, &x->scan);
    if (x->scan.ans_len > 0) {
        judge(x);
        return 1;
    }
    if (x->scan.error != RTU_MBAP_ERR_NONE) {
        x->status = RTU_TCP_BAD_HEADER;
        return 1;
    }
    return 0;
}

int rtu_tcp_xfer_run(rtu_tcp_xfer *x)
{
    short want = POLLIN; /* what the next wait waits for (a TLS read may need to write) */
    int starved = 0;     /* the last read found too little: wait, whatever the layer holds */
    if (x == NULL || x->fd < 0 || x->buf == NULL || x->cap < RTU_TCP_MIN_CAP || x->n > x->cap ||
        x->scan.used > x->n || x->timeout_ns < 0 || x->tid > 0xFFFF || x->unit > 0xFF)
        return RTU_EINVAL;
    if (x->send) {
        size_t keep;
        if (x->pdu == NULL || x->pdu_len < 1 || x->pdu_len > RTU_MBAP_MAX_LENGTH - 1)
            return RTU_EINVAL;
        keep = x->n - x->scan.used; /* a partial ADU of an earlier answer */
        memmove(x->buf, x->buf + x->scan.used, keep);
        x->n = keep;
        memset(&x->scan, 0, sizeof x->scan);
        x->err = x->stage = 0;
        x->end = 0;
        x->start = rtu_now_ns();
        x->deadline = x->start + x->timeout_ns;
        if (transmit(x))
            return RTU_OK;
        if (!x->awaited) { /* a broadcast: nothing comes back */
            x->status = RTU_TCP_ANSWER;
            return RTU_OK;
        }
    }
    if (scanned(x))
        return RTU_OK;
    for (;;) {
        ptrdiff_t got;
        /* step 3: wait for input until the deadline (none when the layer holds
         * bytes already: a whole record may be there, which poll does not see;
         * but after a read that found only part of one, the rest is awaited),
         * then read all there is */
        if (x->io == NULL || starved || x->io->pending(x->io) == 0) {
            int r = rtu_wait_fd(x->fd, want, x->deadline);
            if (r < 0)
                return failed(x, RTU_TCP_STAGE_RECEIVE, errno);
            if (r == 0) {
                x->status = RTU_TCP_TIMEOUT;
                return RTU_OK;
            }
        }
        want = POLLIN;
        starved = 0;
        if (x->cap - x->n < RTU_MBAP_MAX_ADU) {
            /* full of late answers: keep the unresolved bytes only */
            size_t keep = x->n - x->scan.used;
            memmove(x->buf, x->buf + x->scan.used, keep);
            x->n = keep;
            x->scan.used = 0;
        }
        got = x->io != NULL ? x->io->recv(x->io, x->buf + x->n, x->cap - x->n, &want)
                            : recv(x->fd, x->buf + x->n, x->cap - x->n, 0);
        if (got > 0) {
            x->n += (size_t)got;
            x->end = rtu_now_ns();
            if (scanned(x))
                return RTU_OK;
        } else if (got == 0) {
            x->status = RTU_TCP_CLOSED; /* poll said input, recv says the end */
            return RTU_OK;
        } else if (errno != EAGAIN && errno != EWOULDBLOCK) {
            return failed(x, RTU_TCP_STAGE_RECEIVE, errno);
        } else {
            starved = 1;
        }
    }
}

int rtu_tcp_xfer_word(rtu_tcp_xfer *x)
{
    int word = x->status;
    if (x->scan.late != 0 || x->scan.error != RTU_MBAP_ERR_NONE)
        word |= RTU_TCP_NOTE;
    if (x->scan.ans_len != 0) {
        const size_t pdu_len = x->scan.ans_len - RTU_MBAP_HEADER_LEN;
        memcpy(x->answer, x->buf + x->scan.ans_off + RTU_MBAP_HEADER_LEN, pdu_len);
        word |= (int)(pdu_len << 8);
    }
    return word;
}

int rtu_tcp_xfer_call(rtu_tcp_xfer *x, unsigned tid, unsigned unit, const char *pdu, size_t pdu_len,
                      int awaited, int64_t timeout_ns)
{
    int rc;
    if (x == NULL)
        return RTU_EINVAL;
    x->send = 1;
    x->tid = tid;
    x->unit = unit;
    x->pdu = (const uint8_t *)pdu;
    x->pdu_len = pdu_len;
    x->awaited = awaited;
    x->timeout_ns = timeout_ns;
    rc = rtu_tcp_xfer_run(x);
    x->pdu = NULL; /* the caller's bytes: not kept */
    if (rc != RTU_OK)
        return rc;
    return rtu_tcp_xfer_word(x);
}

#else /* no POSIX I/O */

int rtu_tcp_xfer_word(rtu_tcp_xfer *x)
{
    (void)x;
    return RTU_EUNSUPPORTED;
}

int rtu_tcp_xfer_run(rtu_tcp_xfer *x)
{
    (void)x;
    return RTU_EUNSUPPORTED;
}

int rtu_tcp_xfer_call(rtu_tcp_xfer *x, unsigned tid, unsigned unit, const char *pdu, size_t pdu_len,
                      int awaited, int64_t timeout_ns)
{
    (void)x;
    (void)tid;
    (void)unit;
    (void)pdu;
    (void)pdu_len;
    (void)awaited;
    (void)timeout_ns;
    return RTU_EUNSUPPORTED;
}

#endif
