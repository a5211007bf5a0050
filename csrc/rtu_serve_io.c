/*
 * The server engine (declared in rtu_serve.h): a thread that owns a Modbus TCP
 * server's client sockets, answers plain reads from images of the DataStores
 * (rtu_image.c) and hands every other request to Python (the gateway) as an event.
 *
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b; [AP] MODBUS
 * Application Protocol Specification V1.1b3.
 *
 * The state is the caller's memory: the header, then the connections, then the
 * event queue (2 x capacity).  One mutex guards all of it; the thread holds it but
 * while it waits in epoll_wait, so that each call of the caller's takes it for a
 * moment only (nothing here blocks while holding it: every socket is
 * non-blocking).
 *
 * A connection, in the thread (or in rtu_serve_send for its answer):
 *   1. (read) one recv into its buffer of two whole ADUs ([AP] 4.1: an ADU is at
 *      most 260 bytes) when epoll says it is readable and the connection is read;
 *   2. (scan) each complete ADU at the head, in order ([TCP] 3.1.3: the length
 *      field is the only delimiter; rtu_mbap_inspect): an invalid header is a
 *      BAD_HEADER event, and the connection is read no more; a request the
 *      image of its unit answers (rtu_image_answer under rtu_images_lock) is
 *      answered into its output: MBAP header with the request's transaction id,
 *      protocol id 0, length 1 + PDU, the request's unit id ([TCP] 3.1.3), then
 *      the PDU; any other is one REQUEST event, after which the connection is
 *      neither scanned nor read until rtu_serve_send (answers leave in request
 *      order; one REQUEST at most waits per connection);
 *   3. (write) the output is sent at once (MSG_NOSIGNAL | MSG_DONTWAIT); what the
 *      socket does not take waits for EPOLLOUT.  The scan stops while the output
 *      has less room than the longest ADU (and resumes when the socket takes
 *      more); past max_unsent bytes waiting, a STALLED event ends the reading;
 *   4. end of file: once every whole request before it is served, a CLOSED event
 *      (err 0); a socket error: CLOSED with its errno (and nothing more is sent).
 * The epoll key of a connection carries its generation (attaches so far): an event
 * epoll_wait returned before a detach, for a descriptor since reused, is ignored.
 * The wake eventfd carries a key past every connection.
 */
#if defined(__linux__)
#define _GNU_SOURCE
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu_serve.h"

#include "rtu.h"
#include "rtu_image.h"

#if defined(__unix__) || defined(__APPLE__)

#include <pthread.h>

/* The one lock of every image's ranges and values (rtu_serve.h). */
static pthread_mutex_t images_mu = PTHREAD_MUTEX_INITIALIZER;

void rtu_images_lock(void) { pthread_mutex_lock(&images_mu); }

void rtu_images_unlock(void) { pthread_mutex_unlock(&images_mu); }

#else

void rtu_images_lock(void) {}

void rtu_images_unlock(void) {}

#endif

#if defined(__linux__)

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#define MAX_CONNS 65536u
#define EVENTS 64
#define NONE (-1)
#define WAKE_KEY 0xFFFFFFFFu /* the wake eventfd's epoll key (no connection has it) */
#define MAGIC 0x53525645u    /* "SRVE": rtu_serve_init set the memory up */

typedef struct {
    int fd;                         /* -1: not attached */
    uint32_t gen;                   /* attaches so far: an epoll event of an earlier one is stale */
    int watching;                   /* in the epoll set */
    uint32_t events;                /* ... for these */
    int handed;                     /* a REQUEST event of it waits for rtu_serve_send */
    int taken;                      /* ... and rtu_serve_take moved it out */
    int dead;                       /* an ending event (CLOSED, BAD_HEADER, STALLED) was queued: no
                        more reading or scanning */
    int broken;                     /* the socket failed: nothing more is sent either */
    int eof;                        /* recv returned 0 */
    int blocked;                    /* the scan stopped: the output had no room for an answer */
    int resume;                     /* in the resume list (its scan to run again in the thread) */
    int defer;                      /* every request to Python (rtu_serve_defer) */
    const rtu_image *const *routes; /* unit id -> image (the caller's 256), or NULL */
    uint64_t by_function[5];        /* answered by the engine, by function (1..4) */
    int32_t rnext;                  /* the resume list */
    int64_t connected, last_request, partial_since, last_read;
    uint64_t answered;
    size_t in_n, in_used;   /* in[0 .. in_used) resolved, in[in_used .. in_n) not yet */
    size_t out_head, out_n; /* out[out_head .. out_n) unsent */
    uint8_t in[RTU_SERVE_IN_CAP];
    uint8_t out[RTU_SERVE_OUT_CAP];
} serve_conn;

struct rtu_serve {
    uint32_t magic;
    uint32_t capacity;
    uint32_t max_unsent;
    int epfd;
    int evfd;   /* the caller's: readable while events wait */
    int wakefd; /* the thread's */
    int err;
    int stop;
    int running; /* the thread was started (and not yet joined) */
    pthread_t thread;
    pthread_mutex_t mu;
    int32_t rhead, rtail; /* the resume list */
    size_t qhead, qlen, qcap;
    rtu_serve_stats stats;
    /* the REQUEST events of every connection not yet answered: while one waits, no
     * request is answered from an image, so that requests are executed in the order
     * they were read across connections too (a write handed to Python, then a read
     * on another connection: the read sees the write), as the asyncio server does */
    uint32_t handed_now;
    serve_conn *conns;
    rtu_serve_event *queue;
};

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static size_t align16(size_t n) { return (n + 15u) & ~(size_t)15u; }

size_t rtu_serve_size(uint32_t capacity)
{
    if (capacity < 1 || capacity > MAX_CONNS)
        return 0;
    return align16(sizeof(rtu_serve)) + align16(sizeof(serve_conn) * capacity) +
           sizeof(rtu_serve_event) * 2 * (size_t)capacity;
}

/* ---- events and the eventfds ---- */

static void signal_fd(int fd)
{
    const uint64_t one = 1;
    ssize_t w;
    do { /* (an eventfd counter cannot overflow from these) */
        w = write(fd, &one, sizeof one);
    } while (w < 0 && errno == EINTR);
}

static void drain_fd(int fd)
{
    uint64_t v;
    ssize_t r;
    do {
        r = read(fd, &v, sizeof v);
    } while (r < 0 && errno == EINTR);
}

/* Queue an event of connection c (adu: a REQUEST's bytes). */
static rtu_serve_event *queue_event(rtu_serve *s, uint32_t c, int kind, int err, int64_t at)
{
    rtu_serve_event *e;
    if (s->qlen >= s->qcap)
        return NULL; /* (cannot be: two events at most per connection) */
    e = &s->queue[(s->qhead + s->qlen) % s->qcap];
    e->conn = c;
    e->kind = kind;
    e->err = err;
    e->len = 0;
    e->at = at;
    if (s->qlen++ == 0)
        signal_fd(s->evfd); /* readable while events wait */
    return e;
}

/* The connection ends: an ending event, no more reading or scanning. */
static void end(rtu_serve *s, uint32_t c, int kind, int err, int64_t now)
{
    serve_conn *k = &s->conns[c];
    if (k->dead)
        return;
    k->dead = 1;
    queue_event(s, c, kind, err, now);
}

/* ---- epoll ---- */

static void watch(rtu_serve *s, uint32_t c)
{
    serve_conn *k = &s->conns[c];
    uint32_t want = 0;
    struct epoll_event ev;
    if (!k->dead && !k->eof && !k->handed && !k->blocked)
        want |= EPOLLIN;
    if (!k->broken && k->out_n > k->out_head)
        want |= EPOLLOUT;
    if (want == 0) { /* (out of the set: no EPOLLHUP/EPOLLERR wake-ups for nothing) */
        if (k->watching) {
            epoll_ctl(s->epfd, EPOLL_CTL_DEL, k->fd, NULL);
            k->watching = 0;
        }
        return;
    }
    if (k->watching && k->events == want)
        return;
    memset(&ev, 0, sizeof ev);
    ev.events = want;
    ev.data.u64 = (uint64_t)c | ((uint64_t)k->gen << 32);
    if (epoll_ctl(s->epfd, k->watching ? EPOLL_CTL_MOD : EPOLL_CTL_ADD, k->fd, &ev) == 0) {
        k->watching = 1;
        k->events = want;
    }
}

/* ---- the steps ---- */

/* The socket failed (errno err): CLOSED with it, nothing more sent. */
static void fail(rtu_serve *s, uint32_t c, int err, int64_t now)
{
    serve_conn *k = &s->conns[c];
    k->broken = 1;
    end(s, c, RTU_SERVE_CLOSED, err, now);
}

/* Step 3: write what waits, as much as the socket takes now. */
static void flush(rtu_serve *s, uint32_t c, int64_t now)
{
    serve_conn *k = &s->conns[c];
    while (!k->broken && k->out_head < k->out_n) {
        ssize_t w =
            send(k->fd, k->out + k->out_head, k->out_n - k->out_head, MSG_NOSIGNAL | MSG_DONTWAIT);
        if (w > 0) {
            k->out_head += (size_t)w;
            continue;
        }
        if (w < 0 && errno == EINTR)
            continue;
        if (w < 0 && (errno == EAGAIN || errno == EWOULDBLOCK))
            return; /* room later: EPOLLOUT */
        fail(s, c, w < 0 ? errno : EPIPE, now);
        return;
    }
    if (k->out_head == k->out_n)
        k->out_head = k->out_n = 0;
}

/* Room for one more ADU at the end of the output (moving the unsent bytes to the
 * front when that makes it). */
static size_t out_room(serve_conn *k)
{
    if (RTU_SERVE_OUT_CAP - k->out_n < RTU_MBAP_MAX_ADU && k->out_head > 0) {
        memmove(k->out, k->out + k->out_head, k->out_n - k->out_head);
        k->out_n -= k->out_head;
        k->out_head = 0;
    }
    return RTU_SERVE_OUT_CAP - k->out_n;
}

/* After a write: past max_unsent bytes the socket did not take, STALLED. */
static void check_unsent(rtu_serve *s, uint32_t c, int64_t now)
{
    serve_conn *k = &s->conns[c];
    if (!k->broken && k->out_n - k->out_head > s->max_unsent)
        end(s, c, RTU_SERVE_STALLED, 0, now);
}

/* Step 2: the complete ADUs at the head of connection c's buffer, in order. */
static void scan(rtu_serve *s, uint32_t c, int64_t now)
{
    serve_conn *k = &s->conns[c];
    size_t len = 0;
    int err = RTU_MBAP_ERR_NONE;
    k->blocked = 0;
    while (!k->dead && !k->handed) {
        const uint8_t *adu = k->in + k->in_used;
        const rtu_image *img;
        int rc = RTU_IMAGE_DEFER;
        const int st = rtu_mbap_inspect(adu, k->in_n - k->in_used, &len, &err);
        if (st == RTU_MBAP_INVALID) {
            end(s, c, RTU_SERVE_BAD_HEADER, err, now); /* [TCP] 3.1.3: no next ADU */
            break;
        }
        if (st != RTU_MBAP_COMPLETE)
            break;
        if (out_room(k) < RTU_MBAP_MAX_ADU) {
            k->blocked = 1; /* until the socket takes some of the output */
            break;
        }
        s->stats.requests++;
        k->last_request = k->last_read; /* (nothing is read while a scan waits) */
        k->partial_since = 0;
        img = k->defer || k->routes == NULL || s->handed_now ? NULL : k->routes[adu[6]];
        if (img != NULL) {
            size_t n = 0;
            uint8_t *o = k->out + k->out_n;
            rtu_images_lock();
            rc = rtu_image_answer(img, adu + RTU_MBAP_HEADER_LEN, len - RTU_MBAP_HEADER_LEN,
                                  o + RTU_MBAP_HEADER_LEN,
                                  RTU_SERVE_OUT_CAP - k->out_n - RTU_MBAP_HEADER_LEN, &n);
            rtu_images_unlock();
            if (rc == RTU_OK) { /* [TCP] 3.1.3: the request's transaction id and unit */
                o[0] = adu[0];
                o[1] = adu[1];
                o[2] = 0; /* protocol id 0: MODBUS */
                o[3] = 0;
                o[4] = (uint8_t)((n + 1) >> 8); /* length: unit id + PDU */
                o[5] = (uint8_t)((n + 1) & 0xFF);
                o[6] = adu[6];
                k->out_n += RTU_MBAP_HEADER_LEN + n;
                k->answered++;
                s->stats.answered++;
                s->stats.by_function[adu[7]]++; /* (rtu_image_answer: FC 1..4 only) */
                k->by_function[adu[7]]++;
            }
        }
        if (rc != RTU_OK) { /* Python's: one REQUEST event, then nothing until its answer */
            rtu_serve_event *e = queue_event(s, c, RTU_SERVE_REQUEST, 0, k->last_read);
            if (e != NULL) {
                e->len = (uint32_t)len;
                memcpy(e->adu, adu, len);
            }
            k->handed = 1;
            s->handed_now++;
            k->taken = 0;
            s->stats.handed++;
        }
        k->in_used += len;
    }
    if (k->in_used == k->in_n)
        k->in_used = k->in_n = 0;
    /* the request being received: its first byte came with the last read (had it
     * come with an earlier one, that read's scan would have set partial_since, and
     * no request completed since; nothing is read while a scan waits) */
    if (!k->dead && k->in_n > k->in_used &&
        rtu_mbap_inspect(k->in + k->in_used, k->in_n - k->in_used, &len, &err) == RTU_MBAP_NEED) {
        if (k->partial_since == 0)
            k->partial_since = k->last_read;
    } else {
        k->partial_since = 0;
    }
    /* step 4: the end of file once every whole request before it is served */
    if (k->eof && !k->dead && !k->handed && !k->blocked)
        end(s, c, RTU_SERVE_CLOSED, 0, now);
}

/* Scan, write, and again while writing made room for the scan to go on. */
static void service(rtu_serve *s, uint32_t c, int64_t now)
{
    serve_conn *k = &s->conns[c];
    for (;;) {
        scan(s, c, now);
        flush(s, c, now);
        check_unsent(s, c, now);
        if (!k->blocked || k->dead || k->broken || out_room(k) < RTU_MBAP_MAX_ADU)
            break;
    }
    watch(s, c);
}

/* Step 1: one read of connection c. */
static void receive(rtu_serve *s, uint32_t c, int64_t now)
{
    serve_conn *k = &s->conns[c];
    ssize_t got;
    if (RTU_SERVE_IN_CAP - k->in_n < RTU_MBAP_MAX_ADU) { /* keep the unresolved bytes */
        memmove(k->in, k->in + k->in_used, k->in_n - k->in_used);
        k->in_n -= k->in_used;
        k->in_used = 0;
    }
    do {
        got = recv(k->fd, k->in + k->in_n, RTU_SERVE_IN_CAP - k->in_n, MSG_DONTWAIT);
    } while (got < 0 && errno == EINTR);
    if (got > 0) {
        k->in_n += (size_t)got;
        k->last_read = now;
    } else if (got == 0) {
        k->eof = 1;
    } else if (errno != EAGAIN && errno != EWOULDBLOCK) {
        fail(s, c, errno, now);
    }
}

/* Connection c's epoll event. */
static void ready(rtu_serve *s, uint32_t c, uint32_t events, int64_t now)
{
    serve_conn *k = &s->conns[c];
    int tried = 0;
    if ((events & (EPOLLOUT | EPOLLERR | EPOLLHUP)) && k->out_n > k->out_head) {
        flush(s, c, now);
        tried = 1;
    }
    if ((events & (EPOLLIN | EPOLLERR | EPOLLHUP)) && !k->dead && !k->eof && !k->handed &&
        !k->blocked) {
        receive(s, c, now);
        tried = 1;
    }
    if ((events & (EPOLLERR | EPOLLHUP)) && !tried && !k->broken) {
        /* a failure neither a read nor a write saw (neither was due) */
        int soerr = 0;
        socklen_t sl = sizeof soerr;
        if (getsockopt(k->fd, SOL_SOCKET, SO_ERROR, &soerr, &sl) != 0)
            soerr = errno;
        fail(s, c, soerr, now);
    }
    service(s, c, now);
}

static void resume_push(rtu_serve *s, uint32_t c)
{
    serve_conn *k = &s->conns[c];
    if (k->resume)
        return;
    k->resume = 1;
    k->rnext = NONE;
    if (s->rtail != NONE)
        s->conns[s->rtail].rnext = (int32_t)c;
    else
        s->rhead = (int32_t)c;
    s->rtail = (int32_t)c;
}

static void resume_remove(rtu_serve *s, uint32_t c)
{
    int32_t prev = NONE, at = s->rhead;
    if (!s->conns[c].resume)
        return;
    while (at != NONE && at != (int32_t)c) {
        prev = at;
        at = s->conns[at].rnext;
    }
    if (at == NONE)
        return; /* (cannot be) */
    if (prev != NONE)
        s->conns[prev].rnext = s->conns[c].rnext;
    else
        s->rhead = s->conns[c].rnext;
    if (s->rtail == (int32_t)c)
        s->rtail = prev;
    s->conns[c].resume = 0;
    s->conns[c].rnext = NONE;
}

static void *serve_main(void *arg)
{
    rtu_serve *s = (rtu_serve *)arg;
    struct epoll_event evs[EVENTS];
    pthread_mutex_lock(&s->mu);
    while (!s->stop) {
        int n, i;
        int64_t now = now_ns();
        while (s->rhead != NONE) { /* the connections rtu_serve_send answered */
            uint32_t c = (uint32_t)s->rhead;
            s->rhead = s->conns[c].rnext;
            if (s->rhead == NONE)
                s->rtail = NONE;
            s->conns[c].resume = 0;
            s->conns[c].rnext = NONE;
            if (s->conns[c].fd >= 0)
                service(s, c, now);
        }
        pthread_mutex_unlock(&s->mu);
        n = epoll_wait(s->epfd, evs, EVENTS, -1);
        pthread_mutex_lock(&s->mu);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            s->err = errno; /* (the epoll descriptor is gone: nothing more to serve) */
            break;
        }
        now = now_ns();
        for (i = 0; i < n; i++) {
            const uint64_t key = evs[i].data.u64;
            const uint32_t c = (uint32_t)(key & 0xFFFFFFFFu);
            serve_conn *k;
            if (c == WAKE_KEY) {
                drain_fd(s->wakefd);
                continue;
            }
            if (c >= s->capacity)
                continue;
            k = &s->conns[c];
            if (k->fd < 0 || k->gen != (uint32_t)(key >> 32) || !k->watching)
                continue; /* detached since, or out of the set since this batch began */
            ready(s, c, evs[i].events, now);
        }
    }
    pthread_mutex_unlock(&s->mu);
    return NULL;
}

/* ---- the caller's functions ---- */

int rtu_serve_init(rtu_serve *s, uint32_t capacity, uint32_t max_unsent)
{
    uint8_t *p = (uint8_t *)s;
    uint32_t i;
    struct epoll_event ev;
    sigset_t all, old;
    int rc;
    if (s == NULL || capacity < 1 || capacity > MAX_CONNS || max_unsent < 1 || s->magic == MAGIC)
        return RTU_EINVAL; /* (a serve set up already: rtu_serve_destroy first) */
    memset(s, 0, rtu_serve_size(capacity));
    s->capacity = capacity;
    s->max_unsent = max_unsent;
    s->conns = (serve_conn *)(p + align16(sizeof(rtu_serve)));
    s->queue = (rtu_serve_event *)(p + align16(sizeof(rtu_serve)) +
                                   align16(sizeof(serve_conn) * capacity));
    s->qcap = 2 * (size_t)capacity;
    s->rhead = s->rtail = NONE;
    s->epfd = s->evfd = s->wakefd = -1;
    for (i = 0; i < capacity; i++) {
        s->conns[i].fd = -1;
        s->conns[i].rnext = NONE;
    }
    s->epfd = epoll_create1(EPOLL_CLOEXEC);
    if (s->epfd >= 0)
        s->evfd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (s->evfd >= 0)
        s->wakefd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (s->wakefd >= 0) {
        memset(&ev, 0, sizeof ev);
        ev.events = EPOLLIN;
        ev.data.u64 = WAKE_KEY;
        if (epoll_ctl(s->epfd, EPOLL_CTL_ADD, s->wakefd, &ev) != 0) {
            s->err = errno;
            close(s->wakefd);
            s->wakefd = -1;
        }
    } else {
        s->err = errno;
    }
    if (s->wakefd < 0) {
        if (s->evfd >= 0)
            close(s->evfd);
        if (s->epfd >= 0)
            close(s->epfd);
        s->evfd = s->epfd = -1;
        return RTU_ENOSPC;
    }
    if (pthread_mutex_init(&s->mu, NULL) != 0) {
        s->err = ENOMEM;
        close(s->wakefd);
        close(s->evfd);
        close(s->epfd);
        s->wakefd = s->evfd = s->epfd = -1;
        return RTU_ENOSPC;
    }
    sigfillset(&all); /* the thread inherits the mask: no signal handled there */
    pthread_sigmask(SIG_SETMASK, &all, &old);
    rc = pthread_create(&s->thread, NULL, serve_main, s);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (rc != 0) {
        s->err = rc;
        pthread_mutex_destroy(&s->mu);
        close(s->wakefd);
        close(s->evfd);
        close(s->epfd);
        s->wakefd = s->evfd = s->epfd = -1;
        return RTU_ENOSPC;
    }
    s->running = 1;
    s->magic = MAGIC;
    return RTU_OK;
}

void rtu_serve_destroy(rtu_serve *s)
{
    uint32_t i;
    if (s == NULL || s->magic != MAGIC)
        return;
    pthread_mutex_lock(&s->mu);
    s->stop = 1;
    signal_fd(s->wakefd);
    pthread_mutex_unlock(&s->mu);
    pthread_join(s->thread, NULL);
    s->running = 0;
    for (i = 0; i < s->capacity; i++) {
        serve_conn *k = &s->conns[i];
        if (k->fd >= 0) {
            close(k->fd);
            k->fd = -1;
            k->gen++;
        }
    }
    s->qlen = 0;
    close(s->wakefd);
    close(s->evfd);
    close(s->epfd);
    s->wakefd = s->evfd = s->epfd = -1;
    pthread_mutex_destroy(&s->mu);
    s->magic = 0;
}

int rtu_serve_errno(const rtu_serve *s) { return s == NULL ? 0 : s->err; }

int rtu_serve_fd(const rtu_serve *s) { return s == NULL || s->magic != MAGIC ? -1 : s->evfd; }

int rtu_serve_defer(rtu_serve *s, uint32_t conn, int on)
{
    int rc = RTU_OK;
    if (s == NULL || s->magic != MAGIC || conn >= s->capacity)
        return RTU_EINVAL;
    pthread_mutex_lock(&s->mu);
    if (s->conns[conn].fd < 0)
        rc = RTU_EINVAL;
    else
        s->conns[conn].defer = on != 0;
    pthread_mutex_unlock(&s->mu);
    return rc;
}

/* Every image `routes` names passes rtu_image_check (the images lock held). */
static int routes_ok(const rtu_image *const *routes)
{
    int u, rc = RTU_OK;
    if (routes == NULL)
        return RTU_OK;
    rtu_images_lock();
    for (u = 0; u < 256 && rc == RTU_OK; u++)
        if (routes[u] != NULL)
            rc = rtu_image_check(routes[u]);
    rtu_images_unlock();
    return rc;
}

int rtu_serve_attach(rtu_serve *s, uint32_t conn, int fd, const rtu_image *const *routes, int defer)
{
    serve_conn *k;
    int type = 0, flags, rc = RTU_OK;
    socklen_t tl = sizeof type;
    if (s == NULL || s->magic != MAGIC || conn >= s->capacity || fd < 0 ||
        routes_ok(routes) != RTU_OK)
        return RTU_EINVAL;
    pthread_mutex_lock(&s->mu);
    k = &s->conns[conn];
    if (k->fd >= 0 || getsockopt(fd, SOL_SOCKET, SO_TYPE, &type, &tl) != 0 || type != SOCK_STREAM ||
        (flags = fcntl(fd, F_GETFL)) < 0 || fcntl(fd, F_SETFL, flags | O_NONBLOCK) < 0) {
        rc = RTU_EINVAL;
    } else {
        const uint32_t gen = k->gen + 1;
        memset(k, 0, offsetof(serve_conn, in)); /* (the buffers need no clearing) */
        k->gen = gen;
        k->rnext = NONE;
        k->routes = routes;
        k->defer = defer != 0;
        k->fd = fd;
        k->connected = now_ns();
        watch(s, conn);
        if (!k->watching) { /* epoll refuses it */
            s->err = errno;
            k->fd = -1;
            rc = RTU_EINVAL;
        }
    }
    pthread_mutex_unlock(&s->mu);
    return rc;
}

int rtu_serve_detach(rtu_serve *s, uint32_t conn)
{
    serve_conn *k;
    size_t i, kept = 0;
    if (s == NULL || s->magic != MAGIC || conn >= s->capacity)
        return RTU_EINVAL;
    pthread_mutex_lock(&s->mu);
    k = &s->conns[conn];
    if (k->fd < 0) {
        pthread_mutex_unlock(&s->mu);
        return RTU_EINVAL;
    }
    if (k->watching)
        epoll_ctl(s->epfd, EPOLL_CTL_DEL, k->fd, NULL);
    k->watching = 0;
    resume_remove(s, conn);
    for (i = 0; i < s->qlen; i++) { /* its events leave the queue */
        const size_t from = (s->qhead + i) % s->qcap;
        if (s->queue[from].conn == conn)
            continue;
        if (kept != i)
            s->queue[(s->qhead + kept) % s->qcap] = s->queue[from];
        kept++;
    }
    if (kept == 0 && s->qlen > 0)
        drain_fd(s->evfd); /* none waits any more */
    s->qlen = kept;
    close(k->fd);
    k->fd = -1;
    k->gen++;
    if (k->handed)
        s->handed_now--;
    k->handed = k->taken = 0;
    pthread_mutex_unlock(&s->mu);
    return RTU_OK;
}

int rtu_serve_send(rtu_serve *s, uint32_t conn, const uint8_t *adu, size_t len)
{
    serve_conn *k;
    int64_t now;
    if (s == NULL || s->magic != MAGIC || conn >= s->capacity || len > RTU_MBAP_MAX_ADU ||
        (adu == NULL && len > 0))
        return RTU_EINVAL;
    now = now_ns();
    pthread_mutex_lock(&s->mu);
    k = &s->conns[conn];
    if (k->fd < 0 || !k->handed || !k->taken) {
        pthread_mutex_unlock(&s->mu);
        return RTU_EINVAL;
    }
    k->handed = k->taken = 0;
    s->handed_now--;
    if (len > 0 && !k->broken) {
        /* room: the scan handed the request over with room for an ADU left, and
         * only writes happened since */
        if (out_room(k) >= len) {
            memcpy(k->out + k->out_n, adu, len);
            k->out_n += len;
        }
        flush(s, conn, now); /* at once, from this thread */
        check_unsent(s, conn, now);
    }
    resume_push(s, conn); /* the thread scans its buffer again, watches it again */
    signal_fd(s->wakefd);
    pthread_mutex_unlock(&s->mu);
    return RTU_OK;
}

size_t rtu_serve_take(rtu_serve *s, rtu_serve_event *out, size_t cap)
{
    size_t got = 0;
    if (s == NULL || s->magic != MAGIC || out == NULL)
        return 0;
    pthread_mutex_lock(&s->mu);
    while (s->qlen > 0 && got < cap) {
        rtu_serve_event *e = &s->queue[s->qhead];
        if (e->kind == RTU_SERVE_REQUEST)
            s->conns[e->conn].taken = 1;
        out[got++] = *e;
        s->qhead = (s->qhead + 1) % s->qcap;
        s->qlen--;
    }
    if (s->qlen == 0)
        drain_fd(s->evfd);
    pthread_mutex_unlock(&s->mu);
    return got;
}

int rtu_serve_conn(rtu_serve *s, uint32_t conn, rtu_serve_conn_state *st)
{
    serve_conn *k;
    int rc = RTU_OK;
    if (s == NULL || s->magic != MAGIC || conn >= s->capacity || st == NULL)
        return RTU_EINVAL;
    pthread_mutex_lock(&s->mu);
    k = &s->conns[conn];
    if (k->fd < 0) {
        rc = RTU_EINVAL;
    } else {
        st->connected = k->connected;
        st->last_request = k->last_request;
        st->partial_since = k->partial_since;
        st->answered = k->answered;
        memcpy(st->by_function, k->by_function, sizeof st->by_function);
        st->unsent = (uint32_t)(k->out_n - k->out_head);
        st->handed = k->handed ? 1u : 0u;
    }
    pthread_mutex_unlock(&s->mu);
    return rc;
}

int rtu_serve_stats_get(rtu_serve *s, rtu_serve_stats *out)
{
    if (s == NULL || s->magic != MAGIC || out == NULL)
        return RTU_EINVAL;
    pthread_mutex_lock(&s->mu);
    *out = s->stats;
    pthread_mutex_unlock(&s->mu);
    return RTU_OK;
}

#else /* no epoll: the asyncio server runs */

struct rtu_serve {
    int unused;
};

size_t rtu_serve_size(uint32_t capacity)
{
    (void)capacity;
    return 0;
}

int rtu_serve_init(rtu_serve *s, uint32_t capacity, uint32_t max_unsent)
{
    (void)s;
    (void)capacity;
    (void)max_unsent;
    return RTU_EUNSUPPORTED;
}

void rtu_serve_destroy(rtu_serve *s) { (void)s; }

int rtu_serve_errno(const rtu_serve *s)
{
    (void)s;
    return 0;
}

int rtu_serve_fd(const rtu_serve *s)
{
    (void)s;
    return -1;
}

int rtu_serve_defer(rtu_serve *s, uint32_t conn, int on)
{
    (void)s;
    (void)conn;
    (void)on;
    return RTU_EUNSUPPORTED;
}

int rtu_serve_attach(rtu_serve *s, uint32_t conn, int fd, const rtu_image *const *routes, int defer)
{
    (void)s;
    (void)conn;
    (void)fd;
    (void)routes;
    (void)defer;
    return RTU_EUNSUPPORTED;
}

int rtu_serve_detach(rtu_serve *s, uint32_t conn)
{
    (void)s;
    (void)conn;
    return RTU_EUNSUPPORTED;
}

int rtu_serve_send(rtu_serve *s, uint32_t conn, const uint8_t *adu, size_t len)
{
    (void)s;
    (void)conn;
    (void)adu;
    (void)len;
    return RTU_EUNSUPPORTED;
}

size_t rtu_serve_take(rtu_serve *s, rtu_serve_event *out, size_t cap)
{
    (void)s;
    (void)out;
    (void)cap;
    return 0;
}

int rtu_serve_conn(rtu_serve *s, uint32_t conn, rtu_serve_conn_state *st)
{
    (void)s;
    (void)conn;
    (void)st;
    return RTU_EUNSUPPORTED;
}

int rtu_serve_stats_get(rtu_serve *s, rtu_serve_stats *out)
{
    (void)s;
    (void)out;
    return RTU_EUNSUPPORTED;
}

#endif
