/* The clock and the waits of the POSIX I/O files (csrc/rtu_clock_io.c): the
 * master's exchange thread, the TCP transaction and its TLS. */
#ifndef RTU_CLOCK_H
#define RTU_CLOCK_H

#include <stdint.h>

struct pollfd; /* <poll.h>: included by the I/O files only (POSIX) */

/* CLOCK_MONOTONIC in nanoseconds. */
int64_t rtu_now_ns(void);

/* poll() the n descriptors until `t` (absolute CLOCK_MONOTONIC ns; a past `t`: a
 * look), to the nanosecond where ppoll() exists.  >0 ready, 0 the time came, <0
 * error (errno; EINTR: a signal). */
int rtu_poll_until(struct pollfd *p, unsigned n, int64_t t);

/* rtu_poll_until on one descriptor for `events`. */
int rtu_wait_fd(int fd, short events, int64_t t);

#endif
