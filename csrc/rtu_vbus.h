/*
 * pyrtu C core: the virtual bus's wire, as a sans-I/O schedule, and the thin I/O
 * thread that drives it (csrc/rtu_vbus.c, csrc/rtu_vbus_io.c).
 *
 * The schedule (rtu_vbus) models a half-duplex RS-485 line ([SL] 2.1, 3.3): every
 * byte a drop transmits occupies one character time on the wire ([SL] 2.5.1: 1
 * start bit, 8 data bits, parity, stop bits) and reaches every other drop when its
 * last bit is sent; characters of two drops that overlap in time collide.  Input:
 * the bytes a drop wrote and when (rtu_vbus_transmit); output: what each drop
 * receives, in per-drop output buffers that the caller empties after
 * rtu_vbus_service, and when to call it next (rtu_vbus_deadline).  Times are
 * integer nanoseconds on one monotonic clock.  Every state object is allocated by
 * the caller; no clock, no I/O, no allocation.  The pure-Python twin is
 * pyrtu/core/_pure/vbus.py (it adds capture and seeded line faults, which the C
 * schedule leaves to the Python loop).
 *
 * The I/O thread (rtu_vbus_io) reads the drops' pseudo-terminal masters with
 * ppoll(), wakes on absolute CLOCK_MONOTONIC deadlines and writes the deliveries;
 * it returns to its caller only when Python must act (inotify events, an unplug
 * due, a stop request, an error).
 */
#ifndef RTU_VBUS_H
#define RTU_VBUS_H

#include <stddef.h>
#include <stdint.h>

#ifndef RTU_OK
#define RTU_OK 0
#define RTU_EINVAL (-1)
#define RTU_EUNSUPPORTED (-2)
#define RTU_ENOSPC (-3)
#endif

/* a Modbus serial line has at most 247 slaves and a master ([SL] 2.2) */
#define RTU_VBUS_MAX_DROPS 248
/* character slots queued per drop for the wire (a power of two) */
#define RTU_VBUS_QUEUE 4096
/* bytes held (batch fault) or waiting to be written, per drop */
#define RTU_VBUS_OUT 4096
#define RTU_VBUS_NO_TIME INT64_MIN
/* longest character time accepted: 1 s (a 12-bit character at 12 baud) */
#define RTU_VBUS_MAX_CHAR_NS 1000000000
#define RTU_VBUS_MAX_LEAD_NS 10000000

typedef struct {
    uint64_t tx_bytes;       /* bytes the drop wrote that went on the wire */
    uint64_t rx_bytes;       /* bytes written to the drop's client (rtu_vbus_written) */
    uint64_t collided_bytes; /* own bytes corrupted by a collision */
    uint64_t collisions;     /* collision episodes the drop took part in */
    uint64_t overruns;       /* bytes lost: the client's buffer or the output buffer full */
    uint64_t unheard;        /* bytes not delivered: nobody had the drop open */
    uint64_t batches;        /* held bursts released (batch fault) */
} rtu_vbus_drop_counters;

typedef struct {
    /* the character slots queued for the wire: start time and byte (a ring) */
    int64_t q_time[RTU_VBUS_QUEUE];
    uint8_t q_byte[RTU_VBUS_QUEUE];
    uint32_t q_head;
    uint32_t q_len;
    int64_t tx_free;    /* the wire is free for this drop's next character from here */
    int64_t rx_end;     /* end of the last character handed to this drop */
    int64_t last_start; /* the last character this drop put on the wire */
    uint8_t last_byte;
    uint8_t has_last;
    uint8_t alive;        /* plugged in: receives */
    uint8_t cut;          /* transmits nothing more (unplugged or being unplugged) */
    uint8_t echo;         /* receives its own characters */
    uint8_t due;          /* its unplug time has come (set by rtu_vbus_service) */
    int64_t unplug_left;  /* bytes still to transmit before it goes away; -1: none */
    int64_t event_at;     /* when it goes away; RTU_VBUS_NO_TIME: not scheduled */
    int64_t batch_ns;     /* batch fault: hold received bytes this long (0: off) */
    uint32_t batch_bytes; /* ... or until this many are held */
    uint32_t hold_len;
    int64_t hold_deadline; /* RTU_VBUS_NO_TIME: nothing held */
    int64_t hold_end;
    uint32_t out_len;
    int64_t episode;
    rtu_vbus_drop_counters counters;
    uint8_t hold[RTU_VBUS_OUT];
    uint8_t out[RTU_VBUS_OUT];
} rtu_vbus_drop;

typedef struct {
    rtu_vbus_drop *drops;
    uint32_t ndrops;
    int64_t char_ns;
    int64_t lead_ns; /* deliveries are due this early (the hub -> client pty latency) */
    uint64_t wire_bytes;
    uint64_t collisions;
    uint64_t collided;
    int64_t coll_until;
} rtu_vbus;

/* Schedule: `drops` is an array of `ndrops` (1..RTU_VBUS_MAX_DROPS) entries owned by
 * the caller; every drop starts unplugged (rtu_vbus_plug). */
int rtu_vbus_init(rtu_vbus *s, rtu_vbus_drop *drops, uint32_t ndrops, int64_t char_ns,
                  int64_t lead_ns);
int rtu_vbus_plug(rtu_vbus *s, uint32_t drop);
int rtu_vbus_unplug(rtu_vbus *s, uint32_t drop);
int rtu_vbus_set_echo(rtu_vbus *s, uint32_t drop, int on);
/* batch fault: batch_ns >= 0, 1 <= batch_bytes <= RTU_VBUS_OUT */
int rtu_vbus_set_batch(rtu_vbus *s, uint32_t drop, int64_t batch_ns, uint32_t batch_bytes);
/* the drop goes away after `left` more bytes (< 0: no such plan) */
int rtu_vbus_set_unplug_after(rtu_vbus *s, uint32_t drop, int64_t left);
/* the drop transmits nothing more and goes away at `at` */
int rtu_vbus_cut(rtu_vbus *s, uint32_t drop, int64_t at);
/* drop what is held for delivery (a client opened or closed the drop) */
int rtu_vbus_clear_hold(rtu_vbus *s, uint32_t drop);
/* character slots free in the drop's queue: transmit at most this many bytes */
size_t rtu_vbus_space(const rtu_vbus *s, uint32_t drop);
/* bytes the drop's client wrote, read at `now`: queued one character slot after the
 * other.  RTU_ENOSPC (nothing queued) when len > rtu_vbus_space. */
int rtu_vbus_transmit(rtu_vbus *s, uint32_t drop, const uint8_t *data, size_t len, int64_t now);
/* when rtu_vbus_service must run next; RTU_VBUS_NO_TIME: nothing scheduled */
int64_t rtu_vbus_deadline(const rtu_vbus *s);
/* deliver every character whose last bit is sent by now + lead into the output
 * buffers; returns how many drops' unplug time has come (their `due` is set) */
int rtu_vbus_service(rtu_vbus *s, int64_t now);
/* the next drop whose unplug is due (its flag is cleared), or -1 */
int rtu_vbus_take_due(rtu_vbus *s);
/* the caller wrote `n` of the `out_len` bytes of the drop's output (the rest are
 * overruns); heard == 0: nobody had the drop open (all unheard); heard < 0: no
 * pty behind the drop (discarded, not counted) */
int rtu_vbus_written(rtu_vbus *s, uint32_t drop, size_t n, int heard);
/* something is queued, held or pending on the wire */
int rtu_vbus_busy(const rtu_vbus *s);

/* ---- the I/O thread (csrc/rtu_vbus_io.c) ---- */
#define RTU_VBUS_IO_STOPPED 1  /* rtu_vbus_io_stop was called */
#define RTU_VBUS_IO_WATCH 2    /* the watch fd (inotify) is readable */
#define RTU_VBUS_IO_UNPLUG 3   /* a drop's unplug is due: rtu_vbus_take_due */
#define RTU_VBUS_IO_ERRNO (-4) /* a system call failed: rtu_vbus_io_errno */

typedef struct rtu_vbus_io rtu_vbus_io;

size_t rtu_vbus_io_size(void);
/* `io` points to rtu_vbus_io_size() bytes, suitably aligned (malloc's alignment) */
int rtu_vbus_io_init(rtu_vbus_io *io, rtu_vbus *s, int wake_fd, int watch_fd, int64_t anchor_ns);
void rtu_vbus_io_destroy(rtu_vbus_io *io);
void rtu_vbus_io_lock(rtu_vbus_io *io);
void rtu_vbus_io_unlock(rtu_vbus_io *io);
/* with the lock held: the drop's pty master (-1: none) and whether a client listens */
int rtu_vbus_io_set_fd(rtu_vbus_io *io, uint32_t drop, int fd, int heard);
int rtu_vbus_io_set_heard(rtu_vbus_io *io, uint32_t drop, int heard);
/* from any thread: make rtu_vbus_io_run return RTU_VBUS_IO_STOPPED (then write the
 * wake fd) */
void rtu_vbus_io_stop(rtu_vbus_io *io);
int rtu_vbus_io_run(rtu_vbus_io *io);
int rtu_vbus_io_errno(const rtu_vbus_io *io);
int64_t rtu_vbus_io_now(void);
/* wake-ups so far */
uint64_t rtu_vbus_io_wakeups(rtu_vbus_io *io);

#endif
