/*
 * pyrtu C core: the server engine (csrc/rtu_serve_io.c): a thread that owns a
 * Modbus TCP server's client sockets, frames their MBAP requests, answers plain
 * reads (FC 01-04) from the image of the unit's DataStore (rtu_image.h) and hands
 * every other request to Python, in order.
 *
 * [TCP] is the MODBUS Messaging on TCP/IP Implementation Guide V1.0b; [AP] the
 * MODBUS Application Protocol Specification V1.1b3.
 *
 * The caller (the gateway, Python) allocates the state (rtu_serve_size bytes for
 * `capacity` connections), calls rtu_serve_init (which starts the thread), and
 * attaches each accepted socket to a free connection slot with its server's
 * routes (unit id -> image): one serve may carry the connections of many servers.
 * The thread then, for each connection, in request order:
 *   - frames the requests by their MBAP header ([TCP] 3.1.3; an invalid one is a
 *     BAD_HEADER event and the connection is read no more);
 *   - answers a request itself when rtu_image_answer does (under rtu_images_lock):
 *     the answer ADU carries the request's transaction id, protocol id 0, length
 *     1 + PDU and unit id ([TCP] 3.1.3), and is written at once;
 *   - else hands it to Python as a REQUEST event, and reads or scans nothing more
 *     of that connection until Python's answer comes (rtu_serve_send), so that
 *     answers leave in request order and a connection has at most one REQUEST
 *     event waiting;
 *   - while any connection's REQUEST waits for its answer, every request read is
 *     handed over too: requests are executed in the order they were read across
 *     connections as well (a read behind a write sees it, as on the asyncio
 *     server's one thread).
 * Events (REQUEST, CLOSED, BAD_HEADER, STALLED) wait in a queue of 2 x capacity
 * (at most a REQUEST and one ending event per connection: it cannot overflow);
 * rtu_serve_fd is readable while it holds any, and rtu_serve_take moves them out.
 *
 * Memory: each connection buffers RTU_SERVE_IN_CAP bytes of requests and
 * RTU_SERVE_OUT_CAP bytes of answers.  When the answers the socket did not take
 * leave less room than the longest ADU, the engine stops reading that connection
 * until the socket takes more (TCP's flow control then holds the client); past
 * max_unsent bytes waiting (when max_unsent is below that room) the connection is
 * STALLED.
 *
 * Locks: one mutex per serve guards its connections and queue (the thread
 * releases it while it waits in epoll_wait); one process-wide mutex
 * (rtu_images_lock) guards every image's ranges and values.  Lock order: the serve
 * mutex, then the images lock, never the other way: do not call an rtu_serve_*
 * function while holding rtu_images_lock.
 *
 * Linux only (epoll, eventfd, pthreads); elsewhere rtu_serve_size is 0, the other
 * functions return RTU_EUNSUPPORTED (rtu_serve_take 0, rtu_serve_fd -1,
 * rtu_serve_destroy nothing), and the asyncio server runs.
 */
#ifndef RTU_SERVE_H
#define RTU_SERVE_H

#include <stddef.h>
#include <stdint.h>

#include "rtu_image.h"

/* Per connection: the request bytes buffered (two whole ADUs) and the answer bytes
 * that can wait unsent. */
#define RTU_SERVE_IN_CAP 520
#define RTU_SERVE_OUT_CAP 4096

typedef struct rtu_serve rtu_serve; /* caller-allocated: rtu_serve_size bytes */

/* capacity: connections 1..65536; 0 where unsupported (or capacity outside). */
size_t rtu_serve_size(uint32_t capacity);
/* epoll, two eventfds (one the caller watches, one to wake the thread), the mutex;
 * starts the thread (all signals blocked in it).  max_unsent >= 1.  RTU_OK,
 * RTU_EINVAL, RTU_ENOSPC (the system refused a descriptor or the thread: errno in
 * rtu_serve_errno; nothing is left open). */
int rtu_serve_init(rtu_serve *s, uint32_t capacity, uint32_t max_unsent);
/* Wakes and joins the thread, closes every attached socket and its own descriptors
 * (not the memory).  Idempotent (and a no-op on memory rtu_serve_init did not set
 * up, or zeroed memory). */
void rtu_serve_destroy(rtu_serve *s);
int rtu_serve_errno(const rtu_serve *s);
/* The caller's eventfd: readable while events wait (rtu_serve_take reads it empty). */
int rtu_serve_fd(const rtu_serve *s);

/* ONE process-wide mutex guarding every rtu_image's ranges and values: Python holds
 * it while it changes an image; the thread holds it in rtu_image_answer.  Not
 * recursive. */
void rtu_images_lock(void);
void rtu_images_unlock(void);

/* Serve connection slot `conn` (< capacity, free) on `fd`, a connected stream
 * socket the serve owns from now on (set non-blocking here; closed at detach or
 * destroy).  `routes`: the caller's 256 entries, unit id -> the image its reads are
 * answered from (NULL entry: every request to that unit goes to Python; NULL
 * routes: every request), unchanged and alive while the connection is attached
 * (the servers of one serve share it, each connection with its server's routes);
 * `defer`: as rtu_serve_defer.  RTU_OK; RTU_EINVAL (a bad slot, a busy one, not a
 * stream socket, epoll refuses it, or an image rtu_image_check refuses: the caller
 * keeps the descriptor). */
int rtu_serve_attach(rtu_serve *s, uint32_t conn, int fd, const rtu_image *const *routes,
                     int defer);
/* on: every request of `conn` goes to Python (listen-only mode, hooks, DEBUG
 * logging), from its next request on; RTU_EINVAL if not attached. */
int rtu_serve_defer(rtu_serve *s, uint32_t conn, int on);
/* Stop serving it, close its fd, drop its events not yet taken; RTU_EINVAL if not
 * attached. */
int rtu_serve_detach(rtu_serve *s, uint32_t conn);
/* Python's answer to the REQUEST event it took for `conn`: a whole ADU of len
 * 0..260 bytes (0: no answer, e.g. a broadcast).  The bytes go out in order after
 * any answers already queued (written at once, the rest when the socket has
 * room); the connection's further requests are then read and answered again.
 * RTU_EINVAL when conn has no REQUEST taken and not yet answered, or len > 260. */
int rtu_serve_send(rtu_serve *s, uint32_t conn, const uint8_t *adu, size_t len);

typedef struct {
    uint32_t conn;
    int32_t kind; /* RTU_SERVE_* */
    int32_t err;
    uint32_t len;
    int64_t at; /* CLOCK_MONOTONIC ns */
    uint8_t adu[260];
} rtu_serve_event;

/* adu[0..len): a whole request ADU (MBAP header + PDU) Python must answer with
 * rtu_serve_send; at: when it was complete (the read that completed it) */
#define RTU_SERVE_REQUEST 1
/* the client closed (err 0: its end of file, after every whole request before it
 * was served) or the socket failed (err = errno); the connection is no longer read */
#define RTU_SERVE_CLOSED 2
/* an invalid MBAP header (err = RTU_MBAP_ERR_*); no longer read */
#define RTU_SERVE_BAD_HEADER 3
/* more than max_unsent answer bytes wait: the client does not read its answers; no
 * longer read */
#define RTU_SERVE_STALLED 4

/* Moves up to cap events out, oldest first; how many. */
size_t rtu_serve_take(rtu_serve *s, rtu_serve_event *out, size_t cap);

typedef struct {
    int64_t connected;       /* attached (CLOCK_MONOTONIC ns) */
    int64_t last_request;    /* the last complete request (0: none yet) */
    int64_t partial_since;   /* the read that brought the first byte of the request being
                              received (0: none) */
    uint64_t answered;       /* requests the engine answered itself */
    uint64_t by_function[5]; /* [f]: ... of function f (1..4) */
    uint32_t unsent;         /* answer bytes not yet written */
    uint32_t handed;         /* 1 while a REQUEST of it waits for rtu_serve_send */
} rtu_serve_conn_state;

/* RTU_EINVAL if `conn` is not attached. */
int rtu_serve_conn(rtu_serve *s, uint32_t conn, rtu_serve_conn_state *st);

typedef struct {
    uint64_t requests;       /* complete requests read */
    uint64_t answered;       /* by the engine */
    uint64_t handed;         /* to Python (REQUEST events) */
    uint64_t by_function[5]; /* [f]: answered by the engine for FC f (1..4) */
} rtu_serve_stats;

int rtu_serve_stats_get(rtu_serve *s, rtu_serve_stats *out);

#endif
