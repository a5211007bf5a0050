/*
 * One master exchange on a serial descriptor (declared in rtu_xfer.h): the thin
 * I/O step behind a sync master's transaction, run by pyrtu/drivers/sync_io.py
 * through cffi (the GIL is released for the call).
 *
 * Steps, each on the protocol's numbers ([SL] 2.5.1.1 timing, [SL] 2.4.1 timeout):
 *   1. sleep until send_at (absolute CLOCK_MONOTONIC);
 *   2. input pending now is stale: read it, send nothing (RTU_XFER_STALE);
 *   3. write the request (waiting for room if the output buffer is full), tcdrain
 *      on a real line;
 *   4. sleep until end + first_wake, read what came;
 *   5. until `expect` bytes (an exception answer: short_len) or the deadline:
 *      sleep until all but the last character can be in, then wait for input
 *      (the last byte is read as it comes, so its time is the answer's end).
 * A signal (EINTR) ends the step early with what it has (RTU_XFER_SHORT), so that
 * Python runs its handler at once.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu.h"
#include "rtu_xfer.h"

#if defined(__unix__) || defined(__APPLE__)

#include <errno.h>
#include <poll.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* Sleep until `t` (absolute); 0, or EINTR when a signal came first. */
static int sleep_until(int64_t t)
{
#if defined(__linux__)
    struct timespec ts;
    if (t <= now_ns())
        return 0;
    ts.tv_sec = (time_t)(t / 1000000000);
    ts.tv_nsec = (long)(t % 1000000000);
    return clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
#else
    int64_t rel = t - now_ns();
    struct timespec ts;
    if (rel <= 0)
        return 0;
    ts.tv_sec = (time_t)(rel / 1000000000);
    ts.tv_nsec = (long)(rel % 1000000000);
    return nanosleep(&ts, NULL) == 0 ? 0 : errno;
#endif
}

/* Wait for `events` on fd until `t` (absolute; a past `t`: a look).  >0 ready, 0
 * the time came, <0 error (errno; EINTR: a signal). */
static int wait_fd(int fd, short events, int64_t t)
{
    struct pollfd p;
    int64_t rel = t - now_ns();
    p.fd = fd;
    p.events = events;
    p.revents = 0;
    if (rel < 0)
        rel = 0;
#if defined(__linux__)
    {
        struct timespec ts;
        ts.tv_sec = (time_t)(rel / 1000000000);
        ts.tv_nsec = (long)(rel % 1000000000);
        return ppoll(&p, 1, &ts, NULL);
    }
#else
    return poll(&p, 1, (int)((rel + 999999) / 1000000));
#endif
}

/* Read what the descriptor has into buf; 1 bytes came, 0 none (EAGAIN), -1 done
 * (x->status set: an error, or input reported but none given). */
static int take(rtu_xfer *x, int readable)
{
    ssize_t got;
    if (x->n >= x->cap)
        return 0;
    got = read(x->fd, x->buf + x->n, x->cap - x->n);
    if (got > 0) {
        x->n += (size_t)got;
        x->reads++;
        x->last_t = now_ns();
        return 1;
    }
    if (got < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR))
        return 0;
    if (got < 0) {
        x->status = RTU_XFER_ERRNO;
        x->err = errno;
        x->stage = RTU_XFER_STAGE_READ;
        return -1;
    }
    if (readable) { /* poll said input, read says end of file: the device is gone */
        x->status = RTU_XFER_GONE;
        return -1;
    }
    return 0;
}

static int failed(rtu_xfer *x, int stage)
{
    x->status = RTU_XFER_ERRNO;
    x->err = errno;
    x->stage = stage;
    return RTU_OK;
}

/* Step 3: the request on the line. */
static int transmit(rtu_xfer *x)
{
    size_t done = 0;
    int64_t limit;
    x->start = now_ns();
    /* a full output buffer (flow control) may hold the write up to twice its time
     * on the line and a second, as the Python port does */
    limit = x->start + 1000000000 + 2 * (int64_t)x->req_len * x->char_ns;
    while (done < x->req_len) {
        ssize_t w = write(x->fd, x->req + done, x->req_len - done);
        if (w > 0) {
            done += (size_t)w;
            continue;
        }
        if (w < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)
            return failed(x, RTU_XFER_STAGE_WRITE);
        if (now_ns() >= limit) {
            errno = ETIMEDOUT;
            return failed(x, RTU_XFER_STAGE_WRITE);
        }
        if (wait_fd(x->fd, POLLOUT, limit) < 0 && errno != EINTR)
            return failed(x, RTU_XFER_STAGE_WRITE);
    }
    if (x->drain) {
        while (tcdrain(x->fd) != 0) {
            if (errno != EINTR)
                return failed(x, RTU_XFER_STAGE_WRITE);
        }
    }
    x->sent = 1;
    x->end = now_ns();
    if (x->drain && x->end < x->start + (int64_t)x->req_len * x->char_ns)
        x->end = x->start + (int64_t)x->req_len * x->char_ns;
    return RTU_OK;
}

/* The answer's length as far as its bytes tell: an exception answer is shorter. */
static size_t wanted(const rtu_xfer *x)
{
    if (x->short_len > 0 && x->n >= 2 && (x->buf[1] & 0x80) != 0)
        return x->short_len;
    return x->expect;
}

int rtu_xfer_io_run(rtu_xfer *x)
{
    int64_t deadline;
    int r;
    if (x == NULL || x->fd < 0 || x->req == NULL || x->req_len == 0 || x->buf == NULL ||
        x->cap == 0 || x->expect == 0 || x->expect > x->cap || x->short_len > x->expect ||
        x->char_ns <= 0 || x->first_wake < 0 || x->timeout_ns < 0)
        return RTU_EINVAL;
    x->status = RTU_XFER_SHORT;
    x->sent = x->err = x->stage = 0;
    x->start = x->end = x->first_t = x->last_t = 0;
    x->first_n = x->n = 0;
    x->reads = 0;
    /* 1-2: the silence before the request, then a look for stale input */
    if (sleep_until(x->send_at) != 0)
        return RTU_OK; /* a signal: nothing sent */
    r = wait_fd(x->fd, POLLIN, 0);
    if (r > 0) {
        if (take(x, 1) < 0)
            return RTU_OK;
        if (x->n > 0) {
            x->status = RTU_XFER_STALE;
            return RTU_OK;
        }
    }
    if (r < 0) {
        if (errno != EINTR)
            return failed(x, RTU_XFER_STAGE_READ);
        return RTU_OK;
    }
    /* 3 */
    transmit(x);
    if (!x->sent)
        return RTU_OK;
    deadline = x->end + x->timeout_ns;
    /* 4: the first read, where the protocol expects the answer in */
    if (sleep_until(x->end + x->first_wake) != 0)
        return RTU_OK;
    if (take(x, 0) < 0)
        return RTU_OK;
    x->first_n = x->n;
    x->first_t = x->last_t;
    /* 5 */
    while (x->n < wanted(x)) {
        size_t left = wanted(x) - x->n;
        if (x->n > 0 && left > 1) {
            int64_t t = x->last_t + (int64_t)(left - 1) * x->char_ns;
            if (sleep_until(t < deadline ? t : deadline) != 0)
                return RTU_OK;
            if ((r = take(x, 0)) < 0)
                return RTU_OK;
            if (r > 0)
                goto got;
        }
        r = wait_fd(x->fd, POLLIN, deadline);
        if (r < 0) {
            if (errno != EINTR)
                return failed(x, RTU_XFER_STAGE_READ);
            return RTU_OK;
        }
        if (r == 0)
            return RTU_OK; /* the deadline */
        if (take(x, 1) < 0)
            return RTU_OK;
    got:
        if (x->first_n == 0) {
            x->first_n = x->n;
            x->first_t = x->last_t;
        }
    }
    x->status = RTU_XFER_ANSWER;
    return RTU_OK;
}

#else /* no POSIX I/O: the Python driver runs */

int rtu_xfer_io_run(rtu_xfer *x)
{
    (void)x;
    return RTU_EUNSUPPORTED;
}

#endif
