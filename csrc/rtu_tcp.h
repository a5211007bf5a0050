/*
 * pyrtu C core: one Modbus TCP client transaction (the sync master's tcp://),
 * without Python in between.
 *
 * [TCP] is the MODBUS Messaging on TCP/IP Implementation Guide V1.0b.
 *
 * Two parts:
 *   - rtu_tcp_scan (csrc/rtu_tcp.c, portable, no I/O): the ADUs at the head of a
 *     client's receive buffer, judged against the one transaction in flight;
 *   - rtu_tcp_xfer_run (csrc/rtu_tcp_io.c, POSIX): build the request ADU, send
 *     it, wait (poll) for the answer until the deadline, read it whole by the
 *     MBAP length field, and say how it ended as a status code.
 * The pure-Python twin of both is pyrtu/drivers/_pyxfer.py (TcpXferRunner); the
 * Python side (pyrtu/tcp/client.py) turns a status into the error it raised
 * before this file existed.
 */
#ifndef RTU_TCP_H
#define RTU_TCP_H

#include <stddef.h>
#include <stdint.h>

/* What rtu_tcp_scan found at the head of the bytes. */
typedef struct {
    size_t used;         /* bytes resolved: complete ADUs (the answer and late ones) */
    size_t ans_off;      /* the answer's ADU: buf[ans_off .. ans_off + ans_len) */
    size_t ans_len;      /* 0: no answer among the complete ADUs */
    uint32_t late;       /* complete ADUs of another transaction (dropped, counted) */
    uint32_t late_after; /* ... of which after the answer (in the same bytes) */
    int error;           /* RTU_MBAP_ERR_* of an invalid header at `used` (0: none) */
} rtu_tcp_scan_result;

/* Scan buf[pos .. n) for the answer to transaction `tid`, adding to *s (s->used
 * is where to start; a first call sets *s to zeros).  Every complete ADU is
 * resolved ([TCP] 3.1.3: the length field is the only delimiter): the first with
 * transaction id `tid` is the answer (when there is none yet), every other one is
 * late (the answer to a request that timed out: its transaction id, [TCP] 3.1.3,
 * pairs with no request waiting, and the client drops it).  The scan stops at a
 * partial ADU (s->used stays before it: more bytes are needed) or at an invalid
 * header (protocol id other than 0, length outside 2..254: s->error, after which
 * the stream cannot be resynchronised).  RTU_OK, or RTU_EINVAL for NULL. */
int rtu_tcp_scan(const uint8_t *buf, size_t n, unsigned tid, rtu_tcp_scan_result *s);

/* rtu_tcp_xfer_run's results (x->status) */
#define RTU_TCP_ANSWER \
    0                         /* the answer came: a response (or the request of a
                                 broadcast went out, nothing awaited) */
#define RTU_TCP_EXCEPTION 1   /* the answer is an exception response (fc | 0x80) */
#define RTU_TCP_MISMATCH 2    /* the answer names another unit or function */
#define RTU_TCP_TIMEOUT 3     /* the deadline came first */
#define RTU_TCP_CLOSED 4      /* the server closed the connection (end of file) */
#define RTU_TCP_ERRNO 5       /* a system call failed: x->err at x->stage */
#define RTU_TCP_BAD_HEADER 6  /* an invalid MBAP header: x->scan.error */
#define RTU_TCP_INTERRUPTED 7 /* a signal: call again with send = 0 */

/* rtu_tcp_xfer_call's status | this: late answers were dropped (x->scan.late)
 * or an invalid header follows the answer (x->scan.error): more to look at
 * (the status is the low 4 bits, the answer's PDU length from bit 8) */
#define RTU_TCP_NOTE 16

#define RTU_TCP_STAGE_SEND 1
#define RTU_TCP_STAGE_RECEIVE 2

/* The buffers' sizes: the request ADU ([TCP] 3.1.3: 7 + a PDU of 1..253) and
 * the receive buffer (what one recv may bring; late answers kept for the log). */
#define RTU_TCP_REQ_CAP 260
#define RTU_TCP_MIN_CAP 520

/* A layer between the transaction and its socket (MODBUS/TCP Security: TLS,
 * csrc/rtu_tls_io.c); x->io NULL: the socket itself (send/recv).  Each moves
 * bytes without blocking: > 0 bytes moved; 0 the peer closed (recv only); < 0
 * with errno set: EAGAIN (or EWOULDBLOCK) to wait for *want (POLLIN or POLLOUT:
 * a TLS write may need to read and a read to write), any other errno an error.
 * `pending`: bytes the layer holds already (decrypted, not yet read): no wait. */
typedef struct rtu_tcp_io rtu_tcp_io;
struct rtu_tcp_io {
    ptrdiff_t (*send)(rtu_tcp_io *io, const uint8_t *data, size_t len, short *want);
    ptrdiff_t (*recv)(rtu_tcp_io *io, uint8_t *data, size_t len, short *want);
    size_t (*pending)(rtu_tcp_io *io);
};

typedef struct {
    /* what the caller decided */
    int fd;             /* the connected socket (non-blocking) */
    int send;           /* 1: a new transaction (build and send the request);
                            0: go on waiting after RTU_TCP_INTERRUPTED */
    int awaited;        /* 0: a broadcast, nothing read after the send */
    unsigned tid;       /* the transaction id ([TCP] 3.1.3, chosen by the client) */
    unsigned unit;      /* the unit id, 0..255 ([TCP] 4.4.1.2) */
    const uint8_t *pdu; /* the request PDU, 1..253 bytes */
    size_t pdu_len;
    int64_t timeout_ns;           /* the deadline, after the send began */
    uint8_t *buf;                 /* the receive buffer, kept between calls with n and scan:
                            its unresolved bytes buf[scan.used .. n) (a partial ADU
                            read before a timeout) go first at the next send */
    size_t cap;                   /* at least RTU_TCP_MIN_CAP */
    uint8_t req[RTU_TCP_REQ_CAP]; /* the request ADU built here */
    /* what happened */
    int status;
    int err;          /* errno of RTU_TCP_ERRNO */
    int stage;        /* RTU_TCP_STAGE_* of RTU_TCP_ERRNO */
    int64_t start;    /* the send began (CLOCK_MONOTONIC ns) */
    int64_t deadline; /* start + timeout_ns */
    int64_t end;      /* the read that completed the answer returned */
    size_t n;         /* bytes in buf (from 0): late ADUs, the answer, the rest */
    rtu_tcp_scan_result scan;
    uint8_t answer[RTU_TCP_REQ_CAP - 7]; /* rtu_tcp_xfer_call: the answer's PDU */
    rtu_tcp_io *io;                      /* NULL: send/recv on fd; else the layer on it (TLS) */
} rtu_tcp_xfer;

/* Run one transaction (RTU_OK: x->status says how it ended); RTU_EINVAL for a
 * bad argument (nothing sent), RTU_EUNSUPPORTED where there is no POSIX I/O.
 * Start with a zeroed x (n = 0, scan zeroed); then only the inputs change. */
int rtu_tcp_xfer_run(rtu_tcp_xfer *x);

/* One new transaction in one call (the binding's form: a PDU passed as the
 * bytes object's own buffer): fills x's inputs, send = 1, and runs it.  Returns
 * the status (RTU_TCP_*), | RTU_TCP_NOTE when there is more to look at, | the
 * answer's PDU length << 8 when there is an answer (its PDU copied to
 * x->answer); or a negative RTU_E* as rtu_tcp_xfer_run returns. */
int rtu_tcp_xfer_call(rtu_tcp_xfer *x, unsigned tid, unsigned unit, const char *pdu, size_t pdu_len,
                      int awaited, int64_t timeout_ns);
/* rtu_tcp_xfer_call's return word for x as it is (after rtu_tcp_xfer_run with
 * send = 0: the answer's PDU copied to x->answer). */
int rtu_tcp_xfer_word(rtu_tcp_xfer *x);

#endif
