/*
 * pyrtu C core: many Modbus TCP client connections behind one descriptor (the
 * poller's tcp:// buses), without Python per socket.
 *
 * [TCP] is the MODBUS Messaging on TCP/IP Implementation Guide V1.0b.
 *
 * The caller (pyrtu/tcp/_cmux.py) allocates the state (rtu_mux_size bytes for
 * `nconns` connections), connects each socket itself and attaches it; then,
 * from its event loop's thread (no thread here, nothing waits):
 *   - rtu_mux_submit: one request on one connection, sent at once; at most one
 *     transaction per connection is in flight ([TCP] 4.2: a client may wait for
 *     each answer before the next request, which every device takes);
 *   - rtu_mux_fd is an epoll descriptor, readable when any attached socket is:
 *     the caller's loop watches it, and calls rtu_mux_service, which reads every
 *     ready socket, judges each whole answer (rtu_tcp_scan of csrc/rtu_tcp.c:
 *     the MBAP length delimits it, late answers are dropped and counted) and
 *     ends each transaction whose deadline came as a timeout;
 *   - rtu_mux_deadline says when the next timeout is due (a timer of the
 *     caller's calls rtu_mux_service then);
 *   - each ended transaction is one rtu_mux_done record in a queue of `nconns`
 *     (one per connection: it cannot overflow), moved out by rtu_mux_take;
 *   - rtu_mux_repeat: the steady state of a poll, the connection's request sent
 *     again by rtu_mux_service every interval (a new transaction id each time),
 *     until a transaction ends otherwise than with a plain answer or
 *     rtu_mux_unrepeat ends it.
 * So a thousand devices cost the event loop one wake-up and three calls per
 * batch of answers, not a callback per socket, and a poll whose answer does not
 * change costs it no call to send it.
 *
 * The statuses are rtu_tcp.h's RTU_TCP_* (ANSWER, EXCEPTION, MISMATCH, TIMEOUT,
 * CLOSED, ERRNO, BAD_HEADER), with its meanings.  Linux only (epoll); elsewhere
 * rtu_mux_size is 0 and the twin (pyrtu/tcp/_pymux.py) runs.
 */
#ifndef RTU_MUX_H
#define RTU_MUX_H

#include <stddef.h>
#include <stdint.h>

/* One ended transaction. */
typedef struct {
    uint64_t token; /* the caller's, from rtu_mux_submit */
    uint32_t conn;  /* the connection */
    int32_t status; /* RTU_TCP_* */
    int32_t err;    /* errno of RTU_TCP_ERRNO; the MBAP error of BAD_HEADER (also
                        after an answer: the stream is lost after it) */
    int32_t stage;  /* RTU_TCP_STAGE_* of RTU_TCP_ERRNO */
    uint32_t late;  /* late ADUs dropped before the answer */
    uint32_t tid;   /* the transaction id */
    int64_t start;  /* the send began (CLOCK_MONOTONIC ns) */
    int64_t end;    /* the read that completed the answer returned, or the deadline */
    uint32_t flags; /* RTU_MUX_REPEATING, RTU_MUX_RESENT */
    uint32_t len;   /* the answer: unit id and PDU (adu[0] the unit), 0 without one */
    uint8_t adu[254];
} rtu_mux_done;

/* rtu_mux_done.flags: the connection still repeats its request (rtu_mux_repeat)
 * when the record is taken */
#define RTU_MUX_REPEATING 1u
/* ... the transaction was sent by the repeat, not by rtu_mux_submit */
#define RTU_MUX_RESENT 2u

typedef struct rtu_mux rtu_mux;

/* Bytes of state for `nconns` connections (1..65536); 0 where there is no epoll. */
size_t rtu_mux_size(uint32_t nconns);
/* Set up (its epoll descriptor); RTU_OK, RTU_EINVAL, or RTU_ENOSPC when the
 * system refuses a descriptor (errno in rtu_mux_errno). */
int rtu_mux_init(rtu_mux *m, uint32_t nconns);
/* Close what init made (not the memory, not the sockets). */
void rtu_mux_destroy(rtu_mux *m);
/* The epoll descriptor: readable when an attached socket is. */
int rtu_mux_fd(const rtu_mux *m);
/* The connected, non-blocking socket `fd` as connection `conn` (not attached). */
int rtu_mux_attach(rtu_mux *m, uint32_t conn, int fd);
/* Connection `conn` forgotten: its transaction in flight ends with no record, its
 * record not yet taken is dropped; the caller closes the socket. */
int rtu_mux_detach(rtu_mux *m, uint32_t conn);
/* Send request `pdu` (1..253 bytes) to `unit` as transaction `tid` on `conn`, to
 * be answered within timeout_ns (awaited 0: a broadcast, whose record, status
 * RTU_TCP_ANSWER without an answer, comes once it is sent).  RTU_OK: in flight;
 * 1: ended already, its record waits for rtu_mux_take (the send failed, the
 * connection failed while it was idle, a broadcast went out: no descriptor
 * becomes readable for it); RTU_EINVAL (nothing sent) for a bad argument, a
 * connection not attached, or one whose transaction is in flight or whose
 * record is not taken. */
int rtu_mux_submit(rtu_mux *m, uint32_t conn, uint64_t token, unsigned tid, unsigned unit,
                   const char *pdu, size_t pdu_len, int awaited, int64_t timeout_ns);
/* Connection `conn`'s request (its last rtu_mux_submit, awaited) sent again by
 * rtu_mux_service from `first_ns` on, every `interval_ns` (1 ns .. 2^60 ns): at
 * the first service at or after its due time, once the connection's
 * transaction before has ended and its record is taken; then it is due one
 * interval after the time it was due, or at once when that is more than an
 * interval behind (the poller's beat, pyrtu/poller/schedule.py _issue).  Each
 * is a new transaction: the next transaction id, the submit's timeout and
 * token; its record says RTU_MUX_RESENT.  A plain answer (RTU_TCP_ANSWER,
 * nothing late, no error) keeps the repeat going; any other end of a
 * transaction ends it.  RTU_OK, or RTU_EINVAL (nothing changed)
 * for a connection not attached, one with no request since it was attached, a
 * broadcast, one whose record is not taken, or a bad interval. */
int rtu_mux_repeat(rtu_mux *m, uint32_t conn, int64_t first_ns, int64_t interval_ns);
/* Connection `conn`'s repeat ends (if it had one): 1 when a transaction is in
 * flight or its record is not taken yet (that record still comes, without
 * RTU_MUX_REPEATING), 0 when the connection is idle; RTU_EINVAL for a
 * connection not attached. */
int rtu_mux_unrepeat(rtu_mux *m, uint32_t conn);
/* Read what the ready sockets hold, end the transactions due and send the
 * repeats due; the records waiting (>= 0), or RTU_ENOSPC when epoll fails
 * (errno in rtu_mux_errno). */
int rtu_mux_service(rtu_mux *m);
/* When rtu_mux_service is next needed: the first transaction in flight times
 * out, or the first repeat of an idle connection is due (CLOCK_MONOTONIC ns;
 * INT64_MAX: neither). */
int64_t rtu_mux_deadline(const rtu_mux *m);
/* Move up to `cap` records to `out`; how many. */
size_t rtu_mux_take(rtu_mux *m, rtu_mux_done *out, size_t cap);
int rtu_mux_errno(const rtu_mux *m);
/* rtu_mux_service calls since init (the benchmark's wake-ups). */
uint64_t rtu_mux_services(const rtu_mux *m);

#endif
