/*
 * Many Modbus TCP client connections behind one descriptor (declared in
 * rtu_mux.h): the poller's tcp:// buses, driven by pyrtu/tcp/_cmux.py through
 * cffi from the event loop's thread.
 *
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b.
 *
 * The state is the caller's memory: the header, then the connections, then the
 * queue of ended transactions, then each record's generation.  No thread, no
 * clock of the caller's: each call reads CLOCK_MONOTONIC (the clock of Python's
 * time.monotonic) and never waits.
 *
 * A transaction, as csrc/rtu_tcp_io.c runs one on a socket of its own:
 *   1. (submit) the unresolved bytes of the connection's buffer move to its
 *      head; the request ADU is built ([TCP] 3.1.3: MBAP header, transaction id,
 *      protocol id 0, length = 1 + PDU, unit) and sent; what the socket does not
 *      take at once is sent when epoll says it has room;
 *   2. (the loop) each read is scanned (rtu_tcp_scan): late answers are dropped,
 *      an invalid header ends it (the stream cannot be resynchronised);
 *   3. the answer's unit and function are checked against the request's ([TCP]
 *      3.1.3; [AP] 7: an exception response is the function code + 0x80);
 *   4. the busy connections are kept in the order of their deadlines (all of a
 *      poller's have the same timeout, so a new one goes at the tail): the loop
 *      sleeps until the first and ends those whose deadline came as timeouts.
 * Bytes that come while a connection is idle (a late answer) are read and
 * resolved as late; its end of file or error is kept and ends its next
 * transaction at once.
 *
 * A repeat (rtu_mux_repeat) is step 1 again, run by rtu_mux_service for each
 * idle connection whose repeat is due: the same request with the next
 * transaction id ([TCP] 3.1.3: the client picks it to pair the answer).  The
 * due times are an array of their own (8 bytes a connection, scanned whole at
 * each service: a thousand connections' stay in the cache).
 */
#if defined(__linux__)
#define _GNU_SOURCE
#endif

#include "rtu_mux.h"

#include "rtu.h"
#include "rtu_tcp.h"

#if defined(__linux__)

#include <errno.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <sys/types.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

#define MAX_CONNS 65536u
#define EVENTS 256
#define NONE (-1)
#define BUF_CAP RTU_TCP_MIN_CAP         /* two whole ADUs */
#define MAX_INTERVAL ((int64_t)1 << 60) /* ns (36 years): due + interval cannot overflow */

typedef struct {
    int fd;          /* -1: not attached */
    uint32_t gen;    /* attaches so far: an event or record of an earlier one is stale */
    int busy;        /* a transaction in flight */
    int awaited;     /* 0: a broadcast, over once sent */
    int queued;      /* its record waits in the queue */
    int watching;    /* in the epoll set */
    uint32_t events; /* ... for these */
    int broken;      /* an idle connection failed: RTU_TCP_CLOSED/ERRNO/BAD_HEADER (0: no) */
    int broken_err;
    unsigned tid, unit, fc;
    uint64_t token;
    int64_t start, deadline;
    size_t req_len, sent;
    size_t n, used; /* buf[0 .. used) resolved, buf[used .. n) a partial ADU */
    uint32_t late;
    int32_t prev, next; /* the busy connections, by deadline */
    int64_t timeout;    /* the last submit's */
    int repeat;         /* rtu_mux_repeat: its due time in rtu_mux.due */
    int resent;         /* the transaction in flight was sent by the repeat */
    int64_t interval;   /* of the repeat */
    uint8_t req[RTU_TCP_REQ_CAP];
    uint8_t buf[BUF_CAP];
} mux_conn;

struct rtu_mux {
    uint32_t nconns;
    int epfd;
    int err;
    int32_t head, tail;
    size_t qhead, qlen;
    uint64_t services;
    mux_conn *conns;
    rtu_mux_done *done;
    uint32_t *done_gen;
    int64_t *due; /* each connection's next repeat (INT64_MAX: none) */
};

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static size_t align16(size_t n) { return (n + 15u) & ~(size_t)15u; }

size_t rtu_mux_size(uint32_t nconns)
{
    if (nconns < 1 || nconns > MAX_CONNS)
        return 0;
    return align16(sizeof(rtu_mux)) + align16(sizeof(mux_conn) * nconns) +
           align16(sizeof(rtu_mux_done) * nconns) + align16(sizeof(uint32_t) * nconns) +
           sizeof(int64_t) * nconns;
}

int rtu_mux_init(rtu_mux *m, uint32_t nconns)
{
    uint8_t *p = (uint8_t *)m;
    uint32_t i;
    if (m == NULL || nconns < 1 || nconns > MAX_CONNS)
        return RTU_EINVAL;
    memset(m, 0, rtu_mux_size(nconns));
    m->nconns = nconns;
    m->conns = (mux_conn *)(p + align16(sizeof(rtu_mux)));
    m->done = (rtu_mux_done *)(p + align16(sizeof(rtu_mux)) + align16(sizeof(mux_conn) * nconns));
    m->done_gen = (uint32_t *)((uint8_t *)m->done + align16(sizeof(rtu_mux_done) * nconns));
    m->due = (int64_t *)((uint8_t *)m->done_gen + align16(sizeof(uint32_t) * nconns));
    for (i = 0; i < nconns; i++) {
        m->conns[i].fd = -1;
        m->conns[i].prev = m->conns[i].next = NONE;
        m->due[i] = INT64_MAX;
    }
    m->head = m->tail = NONE;
    m->epfd = epoll_create1(EPOLL_CLOEXEC);
    if (m->epfd < 0) {
        m->err = errno;
        return RTU_ENOSPC;
    }
    return RTU_OK;
}

void rtu_mux_destroy(rtu_mux *m)
{
    if (m != NULL && m->epfd >= 0) {
        close(m->epfd);
        m->epfd = -1;
    }
}

int rtu_mux_fd(const rtu_mux *m) { return m == NULL ? -1 : m->epfd; }

static void watch(rtu_mux *m, uint32_t c, uint32_t events)
{
    mux_conn *k = &m->conns[c];
    struct epoll_event ev;
    if (k->watching && k->events == events)
        return; /* (no system call for nothing) */
    memset(&ev, 0, sizeof ev);
    ev.events = events;
    ev.data.u64 = (uint64_t)c | ((uint64_t)k->gen << 32);
    if (epoll_ctl(m->epfd, k->watching ? EPOLL_CTL_MOD : EPOLL_CTL_ADD, k->fd, &ev) == 0) {
        k->watching = 1;
        k->events = events;
    }
}

static void unwatch(rtu_mux *m, uint32_t c)
{
    mux_conn *k = &m->conns[c];
    if (k->watching) {
        epoll_ctl(m->epfd, EPOLL_CTL_DEL, k->fd, NULL);
        k->watching = 0;
    }
}

static void unlink_busy(rtu_mux *m, uint32_t c)
{
    mux_conn *k = &m->conns[c];
    if (k->prev != NONE)
        m->conns[k->prev].next = k->next;
    else
        m->head = k->next;
    if (k->next != NONE)
        m->conns[k->next].prev = k->prev;
    else
        m->tail = k->prev;
    k->prev = k->next = NONE;
}

static void link_busy(rtu_mux *m, uint32_t c)
{
    mux_conn *k = &m->conns[c];
    int32_t after = m->tail; /* the last busy connection due no later than this one */
    while (after != NONE && m->conns[after].deadline > k->deadline)
        after = m->conns[after].prev;
    k->prev = after;
    k->next = after == NONE ? m->head : m->conns[after].next;
    if (k->next != NONE)
        m->conns[k->next].prev = (int32_t)c;
    else
        m->tail = (int32_t)c;
    if (after != NONE)
        m->conns[after].next = (int32_t)c;
    else
        m->head = (int32_t)c;
}

/* Connection c's repeat, if any, ends. */
static void unrepeat(rtu_mux *m, uint32_t c)
{
    m->conns[c].repeat = 0;
    m->due[c] = INT64_MAX;
}

/* The flags of connection c's record (status and err as finish has them, the
 * answer's length): a repeat goes on only through a plain answer. */
static uint32_t judge_repeat(rtu_mux *m, uint32_t c, int status, int err, uint32_t len)
{
    mux_conn *k = &m->conns[c];
    if (k->repeat && (status != RTU_TCP_ANSWER || err != 0 || k->late != 0 || len == 0))
        unrepeat(m, c);
    return k->resent ? RTU_MUX_RESENT : 0u;
}

/* End connection c's transaction with a record (the answer, if any, at
 * buf[ans_off .. ans_off + ans_len)). */
static void finish(rtu_mux *m, uint32_t c, int status, int err, int stage, size_t ans_off,
                   size_t ans_len, int64_t end)
{
    mux_conn *k = &m->conns[c];
    size_t slot = (m->qhead + m->qlen) % m->nconns;
    rtu_mux_done *d = &m->done[slot];
    if (k->busy) {
        k->busy = 0;
        unlink_busy(m, c);
    }
    if (k->queued || m->qlen >= m->nconns)
        return; /* (cannot be: one record per connection, taken before its next submit) */
    d->token = k->token;
    d->conn = c;
    d->status = status;
    d->err = err;
    d->stage = stage;
    d->late = k->late;
    d->tid = k->tid;
    d->start = k->start;
    d->end = end;
    d->len = 0;
    if (ans_len > RTU_MBAP_HEADER_LEN - 1) {
        d->len = (uint32_t)(ans_len - (RTU_MBAP_HEADER_LEN - 1));
        memcpy(d->adu, k->buf + ans_off + RTU_MBAP_HEADER_LEN - 1, d->len);
    }
    d->flags = judge_repeat(m, c, status, err, d->len);
    m->done_gen[slot] = k->gen;
    k->late = 0;
    k->queued = 1;
    m->qlen++;
}

/* The connection cannot carry another transaction (end of file, an error, an
 * invalid header): no more events of it. */
static void lost(rtu_mux *m, uint32_t c) { unwatch(m, c); }

/* Step 2-3 on connection c's bytes: the answer judged, or an invalid header. */
static void scan(rtu_mux *m, uint32_t c, int64_t now)
{
    mux_conn *k = &m->conns[c];
    rtu_tcp_scan_result s;
    memset(&s, 0, sizeof s);
    s.used = k->used;
    rtu_tcp_scan(k->buf, k->n, k->busy ? k->tid : 0x10000u, &s);
    if (!k->busy) { /* idle: whatever is whole is late */
        k->late += s.late + (s.ans_len != 0);
        k->used = s.used;
        if (s.error != RTU_MBAP_ERR_NONE) {
            k->broken = RTU_TCP_BAD_HEADER;
            k->broken_err = s.error;
            lost(m, c);
        }
        return;
    }
    k->late += s.late - s.late_after;
    k->used = s.used;
    if (s.ans_len != 0) {
        const uint8_t *adu = k->buf + s.ans_off;
        int status = RTU_TCP_ANSWER;
        if (adu[6] != k->unit || (adu[7] & 0x7Fu) != k->fc)
            status = RTU_TCP_MISMATCH;
        else if ((adu[7] & 0x80u) != 0)
            status = RTU_TCP_EXCEPTION;
        finish(m, c, status, s.error, 0, s.ans_off, s.ans_len, now);
        k->late = s.late_after;
        if (s.error != RTU_MBAP_ERR_NONE) { /* after the answer: nothing more */
            k->broken = RTU_TCP_BAD_HEADER;
            k->broken_err = s.error;
            lost(m, c);
        }
    } else if (s.error != RTU_MBAP_ERR_NONE) {
        finish(m, c, RTU_TCP_BAD_HEADER, s.error, 0, 0, 0, now);
        k->broken = RTU_TCP_BAD_HEADER;
        k->broken_err = s.error;
        lost(m, c);
    }
}

/* The rest of connection c's request on the socket (step 1). */
static void transmit(rtu_mux *m, uint32_t c, int64_t now)
{
    mux_conn *k = &m->conns[c];
    while (k->sent < k->req_len) {
        ssize_t w =
            send(k->fd, k->req + k->sent, k->req_len - k->sent, MSG_NOSIGNAL | MSG_DONTWAIT);
        if (w > 0) {
            k->sent += (size_t)w;
            continue;
        }
        if (w < 0 && errno == EINTR)
            continue;
        if (w < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            watch(m, c, EPOLLIN | EPOLLOUT); /* room later */
            return;
        }
        finish(m, c, RTU_TCP_ERRNO, w < 0 ? errno : EPIPE, RTU_TCP_STAGE_SEND, 0, 0, now);
        k->broken = RTU_TCP_ERRNO;
        k->broken_err = w < 0 ? errno : EPIPE;
        lost(m, c);
        return;
    }
    watch(m, c, EPOLLIN);
    if (!k->awaited) /* a broadcast: nothing comes back ([AP] 4.1; [TCP] 4.4.1.2) */
        finish(m, c, RTU_TCP_ANSWER, 0, 0, 0, 0, now);
}

/* Connection c is readable: one read, then its bytes scanned.  Their time is
 * when the kernel received them (SO_TIMESTAMPNS, on the realtime clock: moved
 * to the monotonic one by `offset`), not when this read ran: a caller that
 * services the mux on a grid of ticks still learns when each answer came.
 * Linux turns time-stamping on for the whole system a moment after the first
 * socket asks (deferred work): bytes received before that have no time of
 * their own and take the read's. */
static void receive(rtu_mux *m, uint32_t c, int64_t now, int64_t offset)
{
    mux_conn *k = &m->conns[c];
    ssize_t got;
    struct iovec iov;
    struct msghdr msg;
    union {
        char buf[CMSG_SPACE(sizeof(struct timespec))];
        struct cmsghdr align;
    } control;
    if (BUF_CAP - k->n < RTU_MBAP_MAX_ADU) { /* keep the unresolved bytes only */
        memmove(k->buf, k->buf + k->used, k->n - k->used);
        k->n -= k->used;
        k->used = 0;
    }
    iov.iov_base = k->buf + k->n;
    iov.iov_len = BUF_CAP - k->n;
    memset(&msg, 0, sizeof msg);
    msg.msg_iov = &iov;
    msg.msg_iovlen = 1;
    msg.msg_control = control.buf;
    msg.msg_controllen = sizeof control.buf;
    got = recvmsg(k->fd, &msg, MSG_DONTWAIT);
    if (got > 0) {
        int64_t arrived = now;
        struct cmsghdr *cm;
        for (cm = CMSG_FIRSTHDR(&msg); cm != NULL; cm = CMSG_NXTHDR(&msg, cm)) {
            if (cm->cmsg_level == SOL_SOCKET && cm->cmsg_type == SCM_TIMESTAMPNS &&
                cm->cmsg_len >= CMSG_LEN(sizeof(struct timespec))) {
                struct timespec ts;
                memcpy(&ts, CMSG_DATA(cm), sizeof ts);
                arrived = (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec + offset;
                if (arrived > now || arrived < k->start)
                    arrived = now; /* (the realtime clock was stepped) */
            }
        }
        k->n += (size_t)got;
        scan(m, c, arrived);
        return;
    }
    if (got < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR))
        return;
    {
        int status = got == 0 ? RTU_TCP_CLOSED : RTU_TCP_ERRNO;
        int err = got == 0 ? 0 : errno;
        if (k->busy)
            finish(m, c, status, err, RTU_TCP_STAGE_RECEIVE, 0, 0, now);
        k->broken = status;
        k->broken_err = err;
        lost(m, c);
    }
}

int rtu_mux_attach(rtu_mux *m, uint32_t conn, int fd)
{
    mux_conn *k;
    if (m == NULL || conn >= m->nconns || fd < 0)
        return RTU_EINVAL;
    k = &m->conns[conn];
    if (k->fd >= 0) {
        return RTU_EINVAL;
    }
    {
        int on = 1; /* the kernel's time of each read (receive): an optimisation only */
        (void)setsockopt(fd, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on);
    }
    k->fd = fd;
    k->gen++;
    k->busy = k->queued = k->broken = k->broken_err = 0;
    k->n = k->used = 0;
    k->late = 0;
    k->tid = 0;
    k->req_len = k->sent = 0;
    k->resent = 0;
    unrepeat(m, conn);
    watch(m, conn, EPOLLIN);
    return RTU_OK;
}

int rtu_mux_detach(rtu_mux *m, uint32_t conn)
{
    mux_conn *k;
    if (m == NULL || conn >= m->nconns)
        return RTU_EINVAL;
    k = &m->conns[conn];
    if (k->fd < 0) {
        return RTU_EINVAL;
    }
    unwatch(m, conn);
    if (k->busy) {
        k->busy = 0;
        unlink_busy(m, conn);
    }
    if (k->queued) { /* its record leaves the queue (which holds one per connection) */
        size_t i, kept = 0;
        for (i = 0; i < m->qlen; i++) {
            size_t from = (m->qhead + i) % m->nconns;
            if (m->done[from].conn == conn)
                continue;
            if (kept != i) {
                size_t to = (m->qhead + kept) % m->nconns;
                m->done[to] = m->done[from];
                m->done_gen[to] = m->done_gen[from];
            }
            kept++;
        }
        m->qlen = kept;
        k->queued = 0;
    }
    unrepeat(m, conn);
    k->fd = -1;
    k->gen++;
    return RTU_OK;
}

/* Step 1 on idle connection c, whose request is in req: sent as transaction
 * `tid` at `now`; RTU_OK (in flight) or 1 (ended already: its record waits). */
static int begin(rtu_mux *m, uint32_t c, unsigned tid, int64_t now)
{
    mux_conn *k = &m->conns[c];
    memmove(k->buf, k->buf + k->used, k->n - k->used);
    k->n -= k->used;
    k->used = 0;
    k->tid = tid;
    k->start = now;
    k->deadline = k->timeout > INT64_MAX - now ? INT64_MAX : now + k->timeout;
    k->busy = 1;
    link_busy(m, c);
    if (k->broken) { /* it failed while idle: nothing is sent */
        finish(m, c, k->broken, k->broken_err, RTU_TCP_STAGE_RECEIVE, 0, 0, now);
        return 1;
    }
    k->req[0] = (uint8_t)(tid >> 8); /* [TCP] 3.1.3: transaction id */
    k->req[1] = (uint8_t)(tid & 0xFF);
    k->sent = 0;
    transmit(m, c, now);
    if (k->busy)
        scan(m, c, now); /* bytes read before: a whole answer cannot be among them,
                            but an invalid header ends it now */
    return k->busy ? RTU_OK : 1;
}

int rtu_mux_submit(rtu_mux *m, uint32_t conn, uint64_t token, unsigned tid, unsigned unit,
                   const char *pdu, size_t pdu_len, int awaited, int64_t timeout_ns)
{
    mux_conn *k;
    if (m == NULL || conn >= m->nconns || pdu == NULL || pdu_len < 1 ||
        pdu_len > RTU_MBAP_MAX_LENGTH - 1 || tid > 0xFFFF || unit > 0xFF || timeout_ns < 0)
        return RTU_EINVAL;
    k = &m->conns[conn];
    if (k->fd < 0 || k->busy || k->queued) {
        return RTU_EINVAL;
    }
    unrepeat(m, conn); /* (a request of its own: a repeat of another ends) */
    k->token = token;
    k->unit = unit;
    k->fc = (uint8_t)pdu[0];
    k->timeout = timeout_ns;
    k->awaited = awaited != 0;
    k->req[2] = 0; /* [TCP] 3.1.3: protocol id 0, MODBUS */
    k->req[3] = 0;
    k->req[4] = (uint8_t)((pdu_len + 1) >> 8); /* length: unit id + PDU */
    k->req[5] = (uint8_t)((pdu_len + 1) & 0xFF);
    k->req[6] = (uint8_t)unit;
    memcpy(k->req + RTU_MBAP_HEADER_LEN, pdu, pdu_len);
    k->req_len = RTU_MBAP_HEADER_LEN + pdu_len;
    k->resent = 0;
    return begin(m, conn, tid, now_ns());
}

int rtu_mux_repeat(rtu_mux *m, uint32_t conn, int64_t first_ns, int64_t interval_ns)
{
    mux_conn *k;
    if (m == NULL || conn >= m->nconns || interval_ns < 1 || interval_ns > MAX_INTERVAL)
        return RTU_EINVAL;
    k = &m->conns[conn];
    if (k->fd < 0 || k->req_len == 0 || !k->awaited || k->queued)
        return RTU_EINVAL; /* (a record waiting was judged without the repeat) */
    k->repeat = 1;
    k->interval = interval_ns;
    m->due[conn] = first_ns;
    return RTU_OK;
}

int rtu_mux_unrepeat(rtu_mux *m, uint32_t conn)
{
    mux_conn *k;
    if (m == NULL || conn >= m->nconns)
        return RTU_EINVAL;
    k = &m->conns[conn];
    if (k->fd < 0)
        return RTU_EINVAL;
    unrepeat(m, conn);
    return k->busy || k->queued;
}

/* The repeats due by `now` of the idle connections sent (step 1 again). */
static void resend(rtu_mux *m, int64_t now)
{
    uint32_t c;
    for (c = 0; c < m->nconns; c++) {
        int64_t due = m->due[c], next;
        mux_conn *k;
        if (due > now)
            continue;
        k = &m->conns[c];
        if (k->busy || k->queued)
            continue; /* (its turn comes once that ends and is taken) */
        /* its beat (pyrtu/poller/schedule.py _advance): one interval on from when it
         * was due, or from now when that is more than an interval behind */
        next = due + k->interval;
        m->due[c] = next >= now - k->interval ? next : now;
        k->resent = 1;
        begin(m, c, (k->tid + 1u) & 0xFFFFu, now);
    }
}

size_t rtu_mux_take(rtu_mux *m, rtu_mux_done *out, size_t cap)
{
    size_t got = 0;
    if (m == NULL || out == NULL)
        return 0;
    while (m->qlen > 0 && got < cap) {
        size_t slot = m->qhead;
        rtu_mux_done *d = &m->done[slot];
        m->qhead = (m->qhead + 1) % m->nconns;
        m->qlen--;
        if (m->done_gen[slot] != m->conns[d->conn].gen)
            continue; /* (cannot be: detach takes its record out) */
        m->conns[d->conn].queued = 0;
        out[got] = *d;
        if (m->conns[d->conn].repeat)
            out[got].flags |= RTU_MUX_REPEATING;
        got++;
    }
    return got;
}

int rtu_mux_service(rtu_mux *m)
{
    struct epoll_event evs[EVENTS];
    int n, i;
    int64_t now, offset;
    struct timespec real;
    if (m == NULL)
        return RTU_EINVAL;
    m->services++;
    clock_gettime(CLOCK_REALTIME, &real);
    offset = now_ns() - ((int64_t)real.tv_sec * 1000000000 + real.tv_nsec);
    do {
        n = epoll_wait(m->epfd, evs, EVENTS, 0);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            m->err = errno;
            return RTU_ENOSPC;
        }
        now = now_ns();
        for (i = 0; i < n; i++) {
            uint64_t key = evs[i].data.u64;
            uint32_t c = (uint32_t)(key & 0xFFFFFFFFu);
            mux_conn *k;
            if (c >= m->nconns)
                continue;
            k = &m->conns[c];
            if (k->fd < 0 || k->gen != (uint32_t)(key >> 32) || !k->watching)
                continue; /* lost earlier in this batch */
            if ((evs[i].events & EPOLLOUT) && k->busy && k->sent < k->req_len) {
                transmit(m, c, now);
                if (!k->watching)
                    continue;
            }
            if (evs[i].events & (EPOLLIN | EPOLLHUP | EPOLLERR))
                receive(m, c, now, offset);
        }
    } while (n == EVENTS); /* more may be ready */
    /* step 4: the transactions whose deadline came */
    now = now_ns();
    while (m->head != NONE && m->conns[m->head].deadline <= now) {
        uint32_t c = (uint32_t)m->head;
        mux_conn *k = &m->conns[c];
        finish(m, c, RTU_TCP_TIMEOUT, 0, 0, 0, 0, now);
        if (k->sent > 0 && k->sent < k->req_len) {
            /* part of the request is on the wire: the stream cannot carry
             * another ([TCP] 3.1.3: the length field delimits every ADU) */
            k->broken = RTU_TCP_ERRNO;
            k->broken_err = ETIMEDOUT;
            lost(m, c);
        } else if (k->sent < k->req_len) {
            k->sent = k->req_len; /* none of it went out: it never will */
            watch(m, c, EPOLLIN);
        }
    }
    resend(m, now);
    return (int)m->qlen;
}

int64_t rtu_mux_deadline(const rtu_mux *m)
{
    int64_t first;
    uint32_t c;
    if (m == NULL)
        return INT64_MAX;
    first = m->head == NONE ? INT64_MAX : m->conns[m->head].deadline;
    for (c = 0; c < m->nconns; c++)
        if (m->due[c] < first && !m->conns[c].busy)
            first = m->due[c];
    return first;
}

int rtu_mux_errno(const rtu_mux *m) { return m == NULL ? 0 : m->err; }

uint64_t rtu_mux_services(const rtu_mux *m) { return m == NULL ? 0 : m->services; }

#else /* no epoll: the twin runs (pyrtu/tcp/_pymux.py) */

size_t rtu_mux_size(uint32_t nconns)
{
    (void)nconns;
    return 0;
}

int rtu_mux_init(rtu_mux *m, uint32_t nconns)
{
    (void)m;
    (void)nconns;
    return RTU_EUNSUPPORTED;
}

void rtu_mux_destroy(rtu_mux *m) { (void)m; }

int rtu_mux_fd(const rtu_mux *m)
{
    (void)m;
    return -1;
}

int rtu_mux_attach(rtu_mux *m, uint32_t conn, int fd)
{
    (void)m;
    (void)conn;
    (void)fd;
    return RTU_EUNSUPPORTED;
}

int rtu_mux_detach(rtu_mux *m, uint32_t conn)
{
    (void)m;
    (void)conn;
    return RTU_EUNSUPPORTED;
}

int rtu_mux_submit(rtu_mux *m, uint32_t conn, uint64_t token, unsigned tid, unsigned unit,
                   const char *pdu, size_t pdu_len, int awaited, int64_t timeout_ns)
{
    (void)m;
    (void)conn;
    (void)token;
    (void)tid;
    (void)unit;
    (void)pdu;
    (void)pdu_len;
    (void)awaited;
    (void)timeout_ns;
    return RTU_EUNSUPPORTED;
}

int rtu_mux_repeat(rtu_mux *m, uint32_t conn, int64_t first_ns, int64_t interval_ns)
{
    (void)m;
    (void)conn;
    (void)first_ns;
    (void)interval_ns;
    return RTU_EUNSUPPORTED;
}

int rtu_mux_unrepeat(rtu_mux *m, uint32_t conn)
{
    (void)m;
    (void)conn;
    return RTU_EUNSUPPORTED;
}

size_t rtu_mux_take(rtu_mux *m, rtu_mux_done *out, size_t cap)
{
    (void)m;
    (void)out;
    (void)cap;
    return 0;
}

int rtu_mux_service(rtu_mux *m)
{
    (void)m;
    return RTU_EUNSUPPORTED;
}

int64_t rtu_mux_deadline(const rtu_mux *m)
{
    (void)m;
    return INT64_MAX;
}

int rtu_mux_errno(const rtu_mux *m)
{
    (void)m;
    return 0;
}

uint64_t rtu_mux_services(const rtu_mux *m)
{
    (void)m;
    return 0;
}

#endif
