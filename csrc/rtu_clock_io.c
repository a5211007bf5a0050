/*
 * The clock and the waits of the POSIX I/O files (declared in rtu_clock.h), one
 * copy for the exchange thread (rtu_xfer_io.c), the TCP transaction
 * (rtu_tcp_io.c) and its TLS (rtu_tls_io.c): the inter-character and
 * inter-frame silences of [SL] 2.5.1.1 and the [TCP] 4.3 response timeouts are
 * kept to the nanosecond where ppoll() exists.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu_clock.h"

#include <poll.h>
#include <time.h>

int64_t rtu_now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

int rtu_poll_until(struct pollfd *p, unsigned n, int64_t t)
{
    int64_t rel = t - rtu_now_ns();
    if (rel < 0)
        rel = 0;
#if defined(__linux__)
    {
        struct timespec ts;
        ts.tv_sec = (time_t)(rel / 1000000000);
        ts.tv_nsec = (long)(rel % 1000000000);
        return ppoll(p, (nfds_t)n, &ts, NULL);
    }
#else
    return poll(p, (nfds_t)n, (int)((rel + 999999) / 1000000));
#endif
}

int rtu_wait_fd(int fd, short events, int64_t t)
{
    struct pollfd p;
    p.fd = fd;
    p.events = events;
    p.revents = 0;
    return rtu_poll_until(&p, 1, t);
}
