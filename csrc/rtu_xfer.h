/*
 * pyrtu C core: one master xfer on a serial descriptor, without Python in
 * between (csrc/rtu_xfer_io.c).
 *
 * The client protocol (pyrtu/protocol/client.py) decides every time and length:
 * when the request may go (after t3.5 of silence, [SL] 2.5.1.1), when the first
 * read is due (its learned turnaround and the answer's learned length), the
 * deadline (the response timeout, [SL] 2.4.1).  This thin I/O step carries out
 * those decisions in one call: sleep to the send time, look for stale input
 * (then nothing is sent), write, sleep to the first read, read the rest as it
 * comes, and returns what it saw and when, for the protocol to judge.  It keeps
 * no state between calls and decides nothing about the bytes but their count
 * (and an exception answer's shorter length, [MB] 7).  The pure-Python twin is
 * pyrtu/drivers/_pyxfer.py.
 */
#ifndef RTU_XFER_H
#define RTU_XFER_H

#include <stddef.h>
#include <stdint.h>

/* rtu_xfer_io_run's results (x->status) */
#define RTU_XFER_ANSWER 0    /* `expect` bytes came (or an exception answer's `short_len`) */
#define RTU_XFER_STALE 1     /* input was pending at the send time: nothing sent, it is in buf */
#define RTU_XFER_SHORT 2     /* the deadline came (or a signal) with fewer bytes */
#define RTU_XFER_ERRNO 3     /* a system call failed: x->err, x->stage */
#define RTU_XFER_GONE 4      /* the descriptor reported input but gave none (unplugged) */
#define RTU_XFER_CANCELLED 5 /* the cancel descriptor became readable */

/* spin_ns at most (1 ms: a wait on the clock is for the last tens of us) */
#define RTU_XFER_SPIN_MAX 1000000

#define RTU_XFER_STAGE_WRITE 1
#define RTU_XFER_STAGE_READ 2

typedef struct {
    /* what the protocol decided (times: CLOCK_MONOTONIC nanoseconds) */
    int fd;
    int drain;          /* tcdrain() after the write: a real line, not a pty */
    int look;           /* look for stale input before the write (a master) */
    int cancel_fd;      /* readable: end the xfer (-1: none) */
    const uint8_t *req; /* the request ADU */
    size_t req_len;
    int64_t send_at;    /* not before (the silence before the request) */
    int64_t spin_ns;    /* the last ns before send_at waited on the clock, not slept
                           (a sleeping thread wakes tens of us late; 0: none) */
    int64_t first_wake; /* the first read, ns after the end of transmission */
    int64_t timeout_ns; /* the deadline, ns after the end of transmission */
    int64_t char_ns;    /* one character on the line */
    size_t expect;      /* the answer's length (0: none awaited, a slave's response) */
    size_t short_len;   /* the length of an exception answer (0: none) */
    uint8_t *buf;       /* the bytes read: stale input, or the answer */
    size_t cap;
    /* what happened */
    int status;
    int sent;        /* the request was written */
    int err;         /* errno of RTU_XFER_ERRNO */
    int stage;       /* RTU_XFER_STAGE_* of RTU_XFER_ERRNO */
    int64_t start;   /* the write began */
    int64_t end;     /* the transmission ended (after tcdrain; not before its
                           characters' time on a real line) */
    size_t first_n;  /* bytes of the first read of the answer */
    int64_t first_t; /* ... when it returned */
    size_t n;        /* bytes in buf */
    int64_t last_t;  /* when the last read returned */
    uint32_t reads;  /* reads that returned bytes */
} rtu_xfer;

/* Run one xfer (RTU_OK; x->status says how it ended), RTU_EINVAL for a bad
 * argument, RTU_EUNSUPPORTED where there is no POSIX I/O. */
int rtu_xfer_io_run(rtu_xfer *x);

/* A thread of its own that runs xfers for an event loop (AsyncMaster): the
 * caller fills the rtu_xfer it was started with, submits, and watches notify_fd,
 * to which the thread writes one byte when the xfer is over (then x's results
 * and rtu_xfer_worker_rc are valid).  The worker is caller-allocated
 * (rtu_xfer_worker_size bytes) and must not be freed before rtu_xfer_worker_stop
 * returned.  The thread blocks every signal (they are the main thread's). */
#define RTU_EBUSY (-4) /* an xfer is under way */
typedef struct rtu_xfer_worker rtu_xfer_worker;
size_t rtu_xfer_worker_size(void);
int rtu_xfer_worker_start(rtu_xfer_worker *w, rtu_xfer *x, int notify_fd);
int rtu_xfer_worker_submit(rtu_xfer_worker *w);
int rtu_xfer_worker_rc(rtu_xfer_worker *w);
/* ends the thread after the xfer under way (if any) and joins it */
void rtu_xfer_worker_stop(rtu_xfer_worker *w);

#endif
