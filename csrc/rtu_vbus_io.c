/*
 * The virtual bus's thin I/O thread (declared in rtu_vbus.h): reads what clients
 * write to the drops' pseudo-terminal masters, feeds it to the schedule
 * (csrc/rtu_vbus.c) and writes the deliveries at their times.
 *
 * The caller (pyrtu/vbus/hub.py) runs rtu_vbus_io_run from its hub thread; a cffi
 * call releases the GIL, so this loop never waits for Python.  It waits in ppoll()
 * until the next delivery is due (an absolute CLOCK_MONOTONIC deadline, less the
 * measured lateness of a timed wake-up, then a spin of the few microseconds left)
 * or a drop becomes readable, and returns to the caller only when Python has work:
 * an inotify event (a client opened or closed a drop), an unplug due, a stop.  The
 * schedule is shared with the caller's threads under `mu`.
 *
 * POSIX only (pseudo-terminals); elsewhere every function reports
 * RTU_EUNSUPPORTED and the Python loop runs.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu_vbus.h"

#if defined(__unix__) || defined(__APPLE__)

#include <errno.h>
#include <poll.h>
#include <pthread.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#define IDLE_TICK_NS 2000000 /* wake this often when recently active (see below) */
#define WARM_NS 2000000000   /* ... for this long after the last activity */
#define EST_MAX_NS 100000    /* a wake-up lateness estimate is at most this */
#define EST_STEP_NS 1000     /* the estimate moves by this much per timed wake-up */
#define READ_SIZE 4096

struct rtu_vbus_io {
    rtu_vbus *s;
    pthread_mutex_t mu;
    int fd[RTU_VBUS_MAX_DROPS];
    int8_t heard[RTU_VBUS_MAX_DROPS];
    int wake_fd;
    int watch_fd;
    int stop;
    int err;
    int64_t anchor_ns; /* a byte's character started this long before it was read */
    int64_t wake_est;  /* how late a timed ppoll() returns (median, tracked) */
    int64_t warm_until;
    uint64_t wakeups;
    uint8_t buf[READ_SIZE];
};

int64_t rtu_vbus_io_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

size_t rtu_vbus_io_size(void) { return sizeof(struct rtu_vbus_io); }

int rtu_vbus_io_init(rtu_vbus_io *io, rtu_vbus *s, int wake_fd, int watch_fd, int64_t anchor_ns)
{
    uint32_t i;
    if (io == NULL || s == NULL || s->drops == NULL || wake_fd < 0 || anchor_ns < 0 ||
        anchor_ns > RTU_VBUS_MAX_LEAD_NS)
        return RTU_EINVAL;
    memset(io, 0, sizeof *io);
    if (pthread_mutex_init(&io->mu, NULL) != 0)
        return RTU_EINVAL;
    io->s = s;
    for (i = 0; i < RTU_VBUS_MAX_DROPS; i++)
        io->fd[i] = -1;
    io->wake_fd = wake_fd;
    io->watch_fd = watch_fd < 0 ? -1 : watch_fd;
    io->anchor_ns = anchor_ns;
    io->wake_est = 20000;
    io->warm_until = rtu_vbus_io_now() + WARM_NS;
    return RTU_OK;
}

void rtu_vbus_io_destroy(rtu_vbus_io *io)
{
    if (io != NULL && io->s != NULL) {
        pthread_mutex_destroy(&io->mu);
        io->s = NULL;
    }
}

void rtu_vbus_io_lock(rtu_vbus_io *io) { pthread_mutex_lock(&io->mu); }
void rtu_vbus_io_unlock(rtu_vbus_io *io) { pthread_mutex_unlock(&io->mu); }

int rtu_vbus_io_set_fd(rtu_vbus_io *io, uint32_t drop, int fd, int heard)
{
    if (io == NULL || io->s == NULL || drop >= io->s->ndrops)
        return RTU_EINVAL;
    io->fd[drop] = fd < 0 ? -1 : fd;
    io->heard[drop] = heard != 0;
    return RTU_OK;
}

int rtu_vbus_io_set_heard(rtu_vbus_io *io, uint32_t drop, int heard)
{
    if (io == NULL || io->s == NULL || drop >= io->s->ndrops)
        return RTU_EINVAL;
    io->heard[drop] = heard != 0;
    return RTU_OK;
}

void rtu_vbus_io_stop(rtu_vbus_io *io)
{
    pthread_mutex_lock(&io->mu);
    io->stop = 1;
    pthread_mutex_unlock(&io->mu);
}

int rtu_vbus_io_errno(const rtu_vbus_io *io) { return io == NULL ? 0 : io->err; }
/* the I/O thread changes these under the mutex */
uint64_t rtu_vbus_io_wakeups(rtu_vbus_io *io)
{
    uint64_t n;
    if (io == NULL || io->s == NULL)
        return 0;
    pthread_mutex_lock(&io->mu);
    n = io->wakeups;
    pthread_mutex_unlock(&io->mu);
    return n;
}

/* Write every drop's deliveries (non-blocking: what the pty cannot take is an overrun). */
static void flush(rtu_vbus_io *io)
{
    rtu_vbus *s = io->s;
    uint32_t i;
    for (i = 0; i < s->ndrops; i++) {
        rtu_vbus_drop *d = &s->drops[i];
        ssize_t n;
        if (d->out_len == 0)
            continue;
        if (io->fd[i] < 0) {
            rtu_vbus_written(s, i, 0, -1);
            continue;
        }
        if (!io->heard[i]) {
            rtu_vbus_written(s, i, 0, 0);
            continue;
        }
        do {
            n = write(io->fd[i], d->out, d->out_len);
        } while (n < 0 && errno == EINTR);
        rtu_vbus_written(s, i, n < 0 ? 0 : (size_t)n, 1);
    }
}

static void spin_until(int64_t t)
{
    while (rtu_vbus_io_now() < t) {
    }
}

/* Wait until `target` (absolute, CLOCK_MONOTONIC) or an fd is ready; -1: no limit. */
static int wait_fds(struct pollfd *pfd, nfds_t n, int64_t target)
{
#if defined(__linux__)
    struct timespec ts, *tp = NULL;
    if (target != RTU_VBUS_NO_TIME) {
        int64_t rel = target - rtu_vbus_io_now();
        if (rel < 0)
            rel = 0;
        ts.tv_sec = (time_t)(rel / 1000000000);
        ts.tv_nsec = (long)(rel % 1000000000);
        tp = &ts;
    }
    return ppoll(pfd, n, tp, NULL);
#else
    int ms = -1;
    if (target != RTU_VBUS_NO_TIME) {
        int64_t rel = target - rtu_vbus_io_now();
        ms = rel <= 0 ? 0 : (int)((rel + 999999) / 1000000);
    }
    return poll(pfd, n, ms);
#endif
}

int rtu_vbus_io_run(rtu_vbus_io *io)
{
    struct pollfd pfd[RTU_VBUS_MAX_DROPS + 2];
    int owner[RTU_VBUS_MAX_DROPS + 2]; /* drop index, or -1 wake fd, -2 watch fd */
    rtu_vbus *s;
    int rc = RTU_OK;
    if (io == NULL || io->s == NULL)
        return RTU_EINVAL;
    s = io->s;
    pthread_mutex_lock(&io->mu);
    while (rc == RTU_OK) {
        int64_t now = rtu_vbus_io_now(), dl, target, late;
        nfds_t n = 0, k;
        int timed, ready;
        uint32_t i;
        if (io->stop) {
            io->stop = 0; /* one request, one return */
            rc = RTU_VBUS_IO_STOPPED;
            break;
        }
        ready = rtu_vbus_service(s, now);
        flush(io);
        if (ready > 0) {
            rc = RTU_VBUS_IO_UNPLUG;
            break;
        }
        dl = rtu_vbus_deadline(s);
        for (i = 0; i < s->ndrops; i++) {
            /* a full queue reads nothing: the client's writes wait in the pty */
            if (s->drops[i].alive && io->fd[i] >= 0 && rtu_vbus_space(s, i) > 0) {
                pfd[n].fd = io->fd[i];
                pfd[n].events = POLLIN;
                owner[n++] = (int)i;
            }
        }
        pfd[n].fd = io->wake_fd;
        pfd[n].events = POLLIN;
        owner[n++] = -1;
        if (io->watch_fd >= 0) {
            pfd[n].fd = io->watch_fd;
            pfd[n].events = POLLIN;
            owner[n++] = -2;
        }
        pthread_mutex_unlock(&io->mu);

        now = rtu_vbus_io_now();
        if (dl != RTU_VBUS_NO_TIME && dl - now <= io->wake_est) {
            spin_until(dl); /* due within a wake-up's lateness: no sleep */
            pthread_mutex_lock(&io->mu);
            continue;
        }
        target = dl == RTU_VBUS_NO_TIME ? RTU_VBUS_NO_TIME : dl - io->wake_est;
        timed = target != RTU_VBUS_NO_TIME;
        /* Wake at least every 2 ms while recently active: a thread that sleeps
         * longer wakes slower (CPU idle states, VM halts), which would delay
         * noticing a client's write. */
        if (now < io->warm_until && (target == RTU_VBUS_NO_TIME || target - now > IDLE_TICK_NS)) {
            target = now + IDLE_TICK_NS;
            timed = 0;
        }
        ready = wait_fds(pfd, n, target);
        late = ready == 0 && timed ? rtu_vbus_io_now() - target : -1;
        if (late >= 0)
            spin_until(dl);          /* woke early by the estimate's error: the few us left */
        pthread_mutex_lock(&io->mu); /* the fields below are read by other threads */
        io->wakeups++;
        if (late >= 0) { /* track the median lateness of a timed wake-up */
            io->wake_est += late > io->wake_est ? EST_STEP_NS : -EST_STEP_NS;
            if (io->wake_est < 0)
                io->wake_est = 0;
            if (io->wake_est > EST_MAX_NS)
                io->wake_est = EST_MAX_NS;
        }
        if (ready < 0) {
            if (errno != EINTR) {
                io->err = errno;
                rc = RTU_VBUS_IO_ERRNO;
            }
            continue;
        }
        if (ready == 0)
            continue;
        io->warm_until = rtu_vbus_io_now() + WARM_NS;
        for (k = 0; k < n; k++) {
            short ev = pfd[k].revents;
            if (ev == 0)
                continue;
            if (ev & POLLNVAL) { /* an fd closed under the loop: the caller's bug */
                io->err = EBADF;
                rc = RTU_VBUS_IO_ERRNO;
                break;
            }
            if (owner[k] == -1) {
                while (read(io->wake_fd, io->buf, sizeof io->buf) > 0) {
                }
            } else if (owner[k] == -2) {
                rc = RTU_VBUS_IO_WATCH; /* the reads below are done first */
            } else {
                uint32_t d = (uint32_t)owner[k];
                size_t want = rtu_vbus_space(s, d);
                ssize_t got;
                if (io->fd[d] != pfd[k].fd || !s->drops[d].alive || want == 0)
                    continue; /* changed while the loop waited */
                if (want > sizeof io->buf)
                    want = sizeof io->buf;
                got = read(pfd[k].fd, io->buf, want);
                if (got > 0) {
                    rtu_vbus_transmit(s, d, io->buf, (size_t)got,
                                      rtu_vbus_io_now() - io->anchor_ns);
                } else if (got < 0 && errno != EAGAIN && errno != EIO && errno != EINTR) {
                    io->err = errno;
                    rc = RTU_VBUS_IO_ERRNO;
                    break;
                }
            }
        }
    }
    pthread_mutex_unlock(&io->mu);
    return rc;
}

#else /* no POSIX: the Python loop runs */

struct rtu_vbus_io {
    int unused;
};

size_t rtu_vbus_io_size(void) { return sizeof(struct rtu_vbus_io); }
int rtu_vbus_io_init(rtu_vbus_io *io, rtu_vbus *s, int wake_fd, int watch_fd, int64_t anchor_ns)
{
    (void)io;
    (void)s;
    (void)wake_fd;
    (void)watch_fd;
    (void)anchor_ns;
    return RTU_EUNSUPPORTED;
}
void rtu_vbus_io_destroy(rtu_vbus_io *io) { (void)io; }
void rtu_vbus_io_lock(rtu_vbus_io *io) { (void)io; }
void rtu_vbus_io_unlock(rtu_vbus_io *io) { (void)io; }
int rtu_vbus_io_set_fd(rtu_vbus_io *io, uint32_t drop, int fd, int heard)
{
    (void)io;
    (void)drop;
    (void)fd;
    (void)heard;
    return RTU_EUNSUPPORTED;
}
int rtu_vbus_io_set_heard(rtu_vbus_io *io, uint32_t drop, int heard)
{
    (void)io;
    (void)drop;
    (void)heard;
    return RTU_EUNSUPPORTED;
}
void rtu_vbus_io_stop(rtu_vbus_io *io) { (void)io; }
int rtu_vbus_io_run(rtu_vbus_io *io)
{
    (void)io;
    return RTU_EUNSUPPORTED;
}
int rtu_vbus_io_errno(const rtu_vbus_io *io)
{
    (void)io;
    return 0;
}
int64_t rtu_vbus_io_now(void) { return 0; }
uint64_t rtu_vbus_io_wakeups(rtu_vbus_io *io)
{
    (void)io;
    return 0;
}

#endif
