/*
 * One master xfer on a serial descriptor (declared in rtu_xfer.h): the thin
 * I/O step behind a master's transaction, run by pyrtu/drivers/sync_io.py through
 * cffi (the GIL is released for the call), or for an event loop by a worker
 * thread of its own (rtu_xfer_worker, below: pyrtu/drivers/aio.py).
 *
 * Steps, each on the protocol's numbers ([SL] 2.5.1.1 timing, [SL] 2.4.1 timeout):
 *   1. sleep until send_at (absolute CLOCK_MONOTONIC);
 *   2. (look) input pending now is stale: read it, send nothing (RTU_XFER_STALE);
 *   3. write the request (waiting for room if the output buffer is full), tcdrain
 *      on a real line;
 *   4. sleep until end + first_wake, read what came;
 *   5. until `expect` bytes (an exception answer: short_len) or the deadline:
 *      sleep until all but the last character can be in, then wait for input
 *      (the last byte is read as it comes, so its time is the answer's end).
 *   (expect 0: nothing awaited, a slave's response: done after step 3.)
 * A signal (EINTR) ends the step early with what it has (RTU_XFER_SHORT), so that
 * Python runs its handler at once; the cancel descriptor, when readable, ends it too
 * (RTU_XFER_CANCELLED), before the write if it is not due yet.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu.h"
#include "rtu_clock.h"
#include "rtu_xfer.h"

#if defined(__unix__) || defined(__APPLE__)

#include <errno.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>
#if defined(__linux__)
#include <sys/prctl.h>
#endif

/* Sleep until `t` (absolute); 0, or EINTR when a signal came first. */
static int sleep_until(int64_t t)
{
#if defined(__linux__)
    struct timespec ts;
    if (t <= rtu_now_ns())
        return 0;
    ts.tv_sec = (time_t)(t / 1000000000);
    ts.tv_nsec = (long)(t % 1000000000);
    return clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
#else
    int64_t rel = t - rtu_now_ns();
    struct timespec ts;
    if (rel <= 0)
        return 0;
    ts.tv_sec = (time_t)(rel / 1000000000);
    ts.tv_nsec = (long)(rel % 1000000000);
    return nanosleep(&ts, NULL) == 0 ? 0 : errno;
#endif
}

/* Wait on the clock until `t` (absolute): the last tens of microseconds before a
 * write that must be at its time, which a sleep would overshoot by a wake-up's
 * latency (rtu_xfer.spin_ns). */
static void spin_until(int64_t t)
{
    int64_t now = rtu_now_ns();
    while (now < t)
        now = rtu_now_ns();
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
        x->last_t = rtu_now_ns();
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
    x->start = rtu_now_ns();
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
        if (rtu_now_ns() >= limit) {
            errno = ETIMEDOUT;
            return failed(x, RTU_XFER_STAGE_WRITE);
        }
        if (rtu_wait_fd(x->fd, POLLOUT, limit) < 0 && errno != EINTR)
            return failed(x, RTU_XFER_STAGE_WRITE);
    }
    if (x->drain) {
        while (tcdrain(x->fd) != 0) {
            if (errno != EINTR)
                return failed(x, RTU_XFER_STAGE_WRITE);
        }
    }
    x->sent = 1;
    x->end = rtu_now_ns();
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

/* The cancel descriptor became readable (a stop asked for): 1, else 0. */
static int cancelled(const rtu_xfer *x)
{
    struct pollfd p;
    if (x->cancel_fd < 0)
        return 0;
    p.fd = x->cancel_fd;
    p.events = POLLIN;
    p.revents = 0;
    return poll(&p, 1, 0) > 0;
}

/* Sleep until `t` (absolute) watching only the cancel descriptor: 0 the time came,
 * 1 cancelled or a signal (the xfer ends there). */
static int pause_until(rtu_xfer *x, int64_t t)
{
    if (x->cancel_fd < 0)
        return sleep_until(t) != 0;
    while (rtu_now_ns() < t) {
        int r = rtu_wait_fd(x->cancel_fd, POLLIN, t);
        if (r > 0) {
            x->status = RTU_XFER_CANCELLED;
            return 1;
        }
        if (r < 0)
            return 1;
    }
    return 0;
}

/* Wait for input on the line until `t` (absolute), and for the cancel descriptor:
 * >0 input, 0 the time came, <0 the xfer ends (an error, a signal, a cancel). */
static int wait_input(rtu_xfer *x, int64_t t)
{
    struct pollfd p[2];
    nfds_t n = 1;
    int r;
    p[0].fd = x->fd;
    p[0].events = POLLIN;
    p[0].revents = 0;
    if (x->cancel_fd >= 0) {
        p[1].fd = x->cancel_fd;
        p[1].events = POLLIN;
        p[1].revents = 0;
        n = 2;
    }
    r = rtu_poll_until(p, n, t);
    if (r < 0) {
        if (errno != EINTR)
            failed(x, RTU_XFER_STAGE_READ);
        return -1;
    }
    if (n == 2 && p[1].revents != 0) {
        x->status = RTU_XFER_CANCELLED;
        return -1;
    }
    return r > 0 && p[0].revents != 0;
}

int rtu_xfer_io_run(rtu_xfer *x)
{
    int64_t deadline;
    int r;
    if (x == NULL || x->fd < 0 || x->req == NULL || x->req_len == 0 || x->buf == NULL ||
        x->cap == 0 || x->expect > x->cap || x->short_len > x->expect || x->char_ns <= 0 ||
        x->first_wake < 0 || x->timeout_ns < 0 || x->spin_ns < 0 || x->spin_ns > RTU_XFER_SPIN_MAX)
        return RTU_EINVAL;
    x->status = RTU_XFER_SHORT;
    x->sent = x->err = x->stage = 0;
    x->start = x->end = x->first_t = x->last_t = 0;
    x->first_n = x->n = 0;
    x->reads = 0;
    /* 1-2: the silence before the request, then a look for stale input */
    if (cancelled(x)) {
        x->status = RTU_XFER_CANCELLED;
        return RTU_OK;
    }
    if (pause_until(x, x->send_at - x->spin_ns))
        return RTU_OK; /* a signal or a cancel: nothing sent */
    spin_until(x->send_at);
    if (x->look) {
        r = rtu_wait_fd(x->fd, POLLIN, 0);
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
    }
    /* 3 */
    transmit(x);
    if (!x->sent)
        return RTU_OK;
    if (x->expect == 0) { /* nothing awaited (a slave's response) */
        x->status = RTU_XFER_ANSWER;
        return RTU_OK;
    }
    deadline = x->end + x->timeout_ns;
    /* 4: the first read, where the protocol expects the answer in */
    if (pause_until(x, x->end + x->first_wake))
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
            if (pause_until(x, t < deadline ? t : deadline))
                return RTU_OK;
            if ((r = take(x, 0)) < 0)
                return RTU_OK;
            if (r > 0)
                goto got;
        }
        r = wait_input(x, deadline);
        if (r < 0)
            return RTU_OK;
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

/* ------------------------------------------------------------------ the worker */

struct rtu_xfer_worker {
    pthread_t thread;
    pthread_mutex_t mu;
    pthread_cond_t cv;
    rtu_xfer *x;
    int notify_fd;
    int pending; /* submitted, not yet taken by the thread */
    int busy;    /* submitted, not yet over */
    int stop;
    int started;
    int rc; /* rtu_xfer_io_run's return of the last xfer */
};

size_t rtu_xfer_worker_size(void) { return sizeof(struct rtu_xfer_worker); }

static void *worker_main(void *arg)
{
    rtu_xfer_worker *w = (rtu_xfer_worker *)arg;
#if defined(__linux__)
    /* Linux wakes a sleeper up to its timer slack (50 us by default) late: a visible
     * share of t3.5 at 115200 baud ([SL] 2.5.1.1); this thread keeps the line's times */
    prctl(PR_SET_TIMERSLACK, 1000UL, 0UL, 0UL, 0UL);
#endif
    pthread_mutex_lock(&w->mu);
    for (;;) {
        int rc;
        ssize_t k;
        const char one = 1;
        while (!w->pending && !w->stop)
            pthread_cond_wait(&w->cv, &w->mu);
        if (!w->pending)
            break; /* stop, and nothing submitted */
        w->pending = 0;
        pthread_mutex_unlock(&w->mu);
        rc = rtu_xfer_io_run(w->x);
        pthread_mutex_lock(&w->mu);
        w->rc = rc;
        w->busy = 0;
        pthread_mutex_unlock(&w->mu);
        do { /* the loop's wake-up; a full pipe already holds one */
            k = write(w->notify_fd, &one, 1);
        } while (k < 0 && errno == EINTR);
        pthread_mutex_lock(&w->mu);
    }
    pthread_mutex_unlock(&w->mu);
    return NULL;
}

int rtu_xfer_worker_start(rtu_xfer_worker *w, rtu_xfer *x, int notify_fd)
{
    sigset_t all, old;
    int rc;
    if (w == NULL || x == NULL || notify_fd < 0)
        return RTU_EINVAL;
    memset(w, 0, sizeof *w);
    w->x = x;
    w->notify_fd = notify_fd;
    if (pthread_mutex_init(&w->mu, NULL) != 0)
        return RTU_EINVAL;
    if (pthread_cond_init(&w->cv, NULL) != 0) {
        pthread_mutex_destroy(&w->mu);
        return RTU_EINVAL;
    }
    sigfillset(&all); /* the new thread inherits the mask: no signal handled there */
    pthread_sigmask(SIG_SETMASK, &all, &old);
    rc = pthread_create(&w->thread, NULL, worker_main, w);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (rc != 0) {
        pthread_cond_destroy(&w->cv);
        pthread_mutex_destroy(&w->mu);
        return RTU_EINVAL;
    }
    w->started = 1;
    return RTU_OK;
}

int rtu_xfer_worker_submit(rtu_xfer_worker *w)
{
    int rc = RTU_OK;
    if (w == NULL || !w->started)
        return RTU_EINVAL;
    pthread_mutex_lock(&w->mu);
    if (w->busy || w->stop) {
        rc = w->busy ? RTU_EBUSY : RTU_EINVAL;
    } else {
        w->busy = w->pending = 1;
        pthread_cond_signal(&w->cv);
    }
    pthread_mutex_unlock(&w->mu);
    return rc;
}

int rtu_xfer_worker_rc(rtu_xfer_worker *w)
{
    int rc;
    if (w == NULL || !w->started)
        return RTU_EINVAL;
    pthread_mutex_lock(&w->mu);
    rc = w->busy ? RTU_EBUSY : w->rc;
    pthread_mutex_unlock(&w->mu);
    return rc;
}

void rtu_xfer_worker_stop(rtu_xfer_worker *w)
{
    if (w == NULL || !w->started)
        return;
    pthread_mutex_lock(&w->mu);
    w->stop = 1;
    pthread_cond_signal(&w->cv);
    pthread_mutex_unlock(&w->mu);
    pthread_join(w->thread, NULL);
    pthread_cond_destroy(&w->cv);
    pthread_mutex_destroy(&w->mu);
    w->started = 0;
}

#else /* no POSIX I/O: the Python driver runs */

struct rtu_xfer_worker {
    int unused;
};

int rtu_xfer_io_run(rtu_xfer *x)
{
    (void)x;
    return RTU_EUNSUPPORTED;
}
size_t rtu_xfer_worker_size(void) { return sizeof(struct rtu_xfer_worker); }
int rtu_xfer_worker_start(rtu_xfer_worker *w, rtu_xfer *x, int notify_fd)
{
    (void)w;
    (void)x;
    (void)notify_fd;
    return RTU_EUNSUPPORTED;
}
int rtu_xfer_worker_submit(rtu_xfer_worker *w)
{
    (void)w;
    return RTU_EUNSUPPORTED;
}
int rtu_xfer_worker_rc(rtu_xfer_worker *w)
{
    (void)w;
    return RTU_EUNSUPPORTED;
}
void rtu_xfer_worker_stop(rtu_xfer_worker *w) { (void)w; }

#endif
