/*
 * pyrtu C core: public API.
 *
 * Sans-I/O Modbus RTU: bytes and their arrival times (integer microseconds,
 * monotonic) go in, frames and discard events come out.  No clock, no I/O and
 * no allocation anywhere in this library: every state object is allocated by
 * the caller.  Functions return status codes (RTU_OK or a negative RTU_E*),
 * never errno.
 *
 * Specifications cited in comments:
 *   [SL]  MODBUS over Serial Line, Specification and Implementation Guide V1.02
 *   [AP]  MODBUS Application Protocol Specification V1.1b
 *   [CFW] WEG CFW100 Modbus RTU manual (seed 000), sections 4 and 6, Appendix B
 *   [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b
 *   [BV]  Bonfiglioli Vectron ACT/ACU CM-232/CM-485 Modbus manual (seed 004), ch. 6
 */
#ifndef RTU_H
#define RTU_H

#include <stddef.h>
#include <stdint.h>

/* Status codes (shared with rtu_crc.h). */
#ifndef RTU_OK
#define RTU_OK 0
#define RTU_EINVAL (-1)
#define RTU_EUNSUPPORTED (-2)
#define RTU_ENOSPC (-3)
#endif

#include "rtu_crc.h"

/* ---- LRC, ASCII mode ([SL] 2.5.2.2 and 6.2.1; [BV] 6.7.2.3) ---------------- */
uint8_t rtu_lrc(const uint8_t *data, size_t len);

/* ---- Character timing ([SL] 2.5.1.1; [CFW] 4.2.5 table 4.1) ---------------- */
#define RTU_TIMING_MODBUS 0 /* above 19200 baud: t1.5 = 750 us, t3.5 = 1750 us */
#define RTU_TIMING_WEG 1    /* above 19200 baud: char 573 us, t3.5 = 2005 us  */

typedef struct {
    int64_t char_us; /* one character: start + data + parity + stop bits */
    int64_t t15_us;  /* inter-character limit */
    int64_t t35_us;  /* inter-frame silence */
} rtu_timing;

/* bits_per_char: 10 (8N1) or 11 (8E1, 8O1, 8N2), any value 7..12 accepted. */
int rtu_timing_init(rtu_timing *t, uint32_t baudrate, unsigned bits_per_char, int rule);

/* ---- Frame-length prediction ([AP] 6.x PDU layouts; libmodbus-style steps) - */
#define RTU_RULE_NONE 0  /* unknown function in this direction */
#define RTU_RULE_FIXED 1 /* ADU length = add */
#define RTU_RULE_COUNT 2 /* ADU length = off + width + count * mul + add, count big-endian at off */
#define RTU_RULE_MEI 3   /* FC 43: request MEI 0x0E -> 7; response walks the objects */

typedef struct {
    uint8_t type;
    uint8_t off;
    uint8_t width;
    uint8_t mul;
    int16_t add;
} rtu_rule;

#define RTU_DIR_REQUEST 0
#define RTU_DIR_RESPONSE 1

typedef struct {
    rtu_rule rule[2][256]; /* [direction][function code] */
} rtu_rules;

/* Fill with the standard public function codes of [AP]/[SL]. */
void rtu_rules_init(rtu_rules *r);
/* RTU_EINVAL unless function is 1..127 and the rule's shortest ADU is 4..RTU_MAX_ADU_LIMIT
 * bytes (FIXED: add; COUNT: off + width + add, with off >= 2, width 1 or 2, mul >= 1). */
int rtu_rules_set(rtu_rules *r, int direction, unsigned function, rtu_rule rule);

/* Prediction result. */
#define RTU_PRED_LENGTH 0  /* *length is the ADU length */
#define RTU_PRED_NEED 1    /* more bytes needed; *length is the minimum to decide */
#define RTU_PRED_UNKNOWN 2 /* no rule for this function in this direction */

/* RTU_PRED_UNKNOWN for a direction other than RTU_DIR_REQUEST / RTU_DIR_RESPONSE. */
int rtu_predict(const rtu_rules *r, int direction, const uint8_t *adu, size_t n, size_t *length);

/* The shortest answer to a request (address, function): the response's
 * shortest length from the rules, or the 5-byte exception response ([AP] 7)
 * when shorter; 4 (the shortest RTU frame) when no rule knows the response. */
size_t rtu_answer_min(const rtu_rules *r, uint8_t address, uint8_t function);

/* ---- Frames and events -------------------------------------------------- */
#define RTU_KIND_REQUEST 0
#define RTU_KIND_RESPONSE 1
#define RTU_KIND_EXCEPTION 2
#define RTU_KIND_UNKNOWN 3
#define RTU_KIND_DISCARD 4

#define RTU_ERR_NONE 0
#define RTU_ERR_CRC 1
#define RTU_ERR_T15 2
#define RTU_ERR_OVERFLOW 3
#define RTU_ERR_UNKNOWN_FUNCTION 4
#define RTU_ERR_TRUNCATED 5
#define RTU_NERR 6

#define RTU_ROLE_MASTER 0
#define RTU_ROLE_SLAVE 1
#define RTU_ROLE_MONITOR 2

#define RTU_NO_TIME INT64_MIN

#define RTU_MAX_ADU_LIMIT 1024

typedef struct {
    uint64_t offset; /* stream position of the first byte */
    uint32_t length; /* bytes */
    uint8_t kind;    /* RTU_KIND_* */
    uint8_t error;   /* RTU_ERR_* (RTU_ERR_NONE for frames) */
    uint16_t reserved;
    int64_t start_us; /* start of the first character on the wire, or RTU_NO_TIME */
    int64_t end_us;   /* end of the last character, or RTU_NO_TIME */
} rtu_event;

/* A position in the stream that follows a silence: flags RTU_MARK_T15 (silence
 * longer than t1.5) and RTU_MARK_T35 (silence of t3.5 or more). */
#define RTU_MARK_T15 1
#define RTU_MARK_T35 2
typedef struct {
    uint64_t pos;
    uint32_t flags;
    uint32_t reserved;
} rtu_mark;

typedef struct {
    int role;
    int strict;
    uint32_t max_adu;
    rtu_timing timing;
    int64_t flush_us; /* lenient mode: incomplete bytes are dropped after this silence */
    rtu_rules rules;
} rtu_config;

int rtu_config_init(rtu_config *c, int role, uint32_t baudrate, unsigned bits_per_char, int rule);

/* Context carried between frames (which request awaits a response). */
typedef struct {
    int pending;
    uint8_t address;
    uint8_t function;
} rtu_context;

typedef struct {
    uint64_t frames[4];           /* by kind: request, response, exception, unknown */
    uint64_t discarded[RTU_NERR]; /* bytes by error reason */
    uint64_t discard_events;
} rtu_counters;

/* ---- The framer: incremental, sans-I/O --------------------------------- */
#define RTU_FRAMER_CAP (2 * RTU_MAX_ADU_LIMIT)

typedef struct {
    rtu_config cfg;
    rtu_context ctx;
    rtu_counters counters;
    uint8_t buf[RTU_FRAMER_CAP];
    int64_t times[RTU_FRAMER_CAP]; /* arrival (end of character) of each byte */
    rtu_mark marks[RTU_FRAMER_CAP];
    size_t nmarks;
    size_t head;     /* first unresolved byte */
    size_t n;        /* bytes in buf */
    uint64_t base;   /* stream position of buf[0] */
    int64_t last_us; /* arrival of the last byte, RTU_NO_TIME before any */
    int silent;      /* a silence of t3.5 follows the last byte */
    int final;       /* nothing more joins the buffered bytes */
    uint32_t run;    /* pending discard run, in bytes (ending at head) */
    uint8_t run_error;
    rtu_event event; /* the event returned by the last rtu_framer_poll */
} rtu_framer;

int rtu_framer_init(rtu_framer *f, const rtu_config *cfg);
void rtu_framer_reset(rtu_framer *f);
/* Accept bytes that arrived at now_us; returns how many were taken (the rest
 * must be offered again after rtu_framer_poll returned 0). */
size_t rtu_framer_feed(rtu_framer *f, const uint8_t *data, size_t len, int64_t now_us);
/* Silence up to now_us. */
void rtu_framer_handle_timer(rtu_framer *f, int64_t now_us);
/* Absolute time at which rtu_framer_handle_timer should run, INT64_MAX if none
 * (or if it would lie beyond INT64_MAX: time arithmetic saturates). */
int64_t rtu_framer_deadline(const rtu_framer *f);
/* 1: f->event holds an event whose bytes are at rtu_framer_event_data(f) until
 * the next call; 0: nothing more until new bytes or a timer. */
int rtu_framer_poll(rtu_framer *f);
const uint8_t *rtu_framer_event_data(const rtu_framer *f);
/* The local side transmitted an ADU (sets or clears the context). */
void rtu_framer_sent(rtu_framer *f, const uint8_t *adu, size_t len);

/* Bytes still needed, a lower bound a driver may sleep on (needed x character
 * time) before it looks again; call it after rtu_framer_poll returned 0.
 *   - Bytes pending: the least, over the directions rtu_framer_poll tries at
 *     the head (and over a head that starts after a t3.5 silence inside the
 *     pending bytes), of the shortest frame the prediction rules allow for
 *     the bytes so far, minus the bytes pending.  One pending byte: 1 (the
 *     function code decides), or, in the master role when it is the awaited
 *     slave's address, the shortest answer (rtu_answer_min) minus 1.
 *   - Nothing pending: in the master role after rtu_framer_sent of a request
 *     that awaits an answer, the shortest answer (rtu_answer_min); else 0.
 *   - 0 also when no rule predicts the head (unknown function, a length past
 *     max_adu), or when every predicted candidate is complete and only a
 *     silence can end the head: wake on the next byte or the deadline.
 * More bytes can arrive before a frame ends (a longer answer, noise); fewer
 * never end one by its length.  Silences end frames by time, not by bytes:
 * rtu_framer_deadline covers them. */
size_t rtu_framer_needed(const rtu_framer *f);

/* ---- Bulk stream parser ------------------------------------------------- */
typedef struct {
    const rtu_config *cfg;
    rtu_context ctx;
    rtu_counters counters;
    uint64_t pos;      /* next unresolved byte */
    size_t mark_index; /* first mark with pos > this->pos */
    uint32_t run;
    uint8_t run_error;
    uint64_t run_start;
    size_t chunk_index; /* cursor for byte times */
} rtu_parser;

/* Marks from chunk times (chunk i starts at offsets[i], all its bytes arrived
 * by times[i]); out must hold nchunks marks.  RTU_EINVAL for offsets that do
 * not start at 0 and ascend within total, or t->char_us <= 0. */
int rtu_marks_from_chunks(const rtu_timing *t, const uint64_t *offsets, const int64_t *times,
                          size_t nchunks, uint64_t total, rtu_mark *out, size_t *nout);

/* RTU_EINVAL for a config rtu_framer_init would refuse too (max_adu outside
 * 4..RTU_MAX_ADU_LIMIT, char_us <= 0, negative t1.5/t3.5, flush_us < t3.5). */
int rtu_parser_init(rtu_parser *p, const rtu_config *cfg);
/* Parse data[0..len) into out (capacity cap); *nout receives the count.
 * Returns RTU_OK when the whole buffer is done, RTU_ENOSPC when out is full
 * (call again with the same data, marks and chunks and a fresh out array to
 * continue: the events of all calls are those of one call with a large out).
 * Any cap >= 1 makes progress; cap == 0 with work left is RTU_EINVAL.  Marks
 * must ascend by pos (rtu_marks_from_chunks makes them so). */
int rtu_parse(rtu_parser *p, const uint8_t *data, size_t len, const rtu_mark *marks, size_t nmarks,
              const uint64_t *offsets, const int64_t *times, size_t nchunks, rtu_event *out,
              size_t cap, size_t *nout);

/* ---- Modbus TCP: MBAP framing ([TCP] 3.1.3; csrc/rtu_mbap.c) ------------ */
#define RTU_MBAP_HEADER_LEN 7   /* transaction id, protocol id, length, unit id */
#define RTU_MBAP_MIN_LENGTH 2   /* length field: unit id + a PDU of 1..253 bytes */
#define RTU_MBAP_MAX_LENGTH 254 /* ([AP] 4.1) */
#define RTU_MBAP_MAX_ADU 260
#define RTU_MBAP_FRAMER_CAP (2 * RTU_MBAP_MAX_ADU)

/* rtu_mbap_inspect results */
#define RTU_MBAP_COMPLETE 0 /* *length: the ADU is data[0..*length) */
#define RTU_MBAP_NEED 1     /* *length: the ADU length known so far (7 until the length field) */
#define RTU_MBAP_INVALID 2  /* *error: why the header is invalid */

/* Why bytes were discarded (event error codes) */
#define RTU_MBAP_ERR_NONE 0
#define RTU_MBAP_ERR_PROTOCOL 1  /* protocol id other than 0 */
#define RTU_MBAP_ERR_LENGTH 2    /* length field outside 2..254 */
#define RTU_MBAP_ERR_TRUNCATED 3 /* the stream ended inside an ADU */
#define RTU_MBAP_NERR 4

typedef struct {
    uint64_t offset; /* stream position of the first byte */
    uint64_t length; /* bytes of the ADU, or of the discarded run */
    uint8_t kind;    /* RTU_KIND_* (RTU_KIND_DISCARD with an error) */
    uint8_t error;   /* RTU_MBAP_ERR_* */
    uint16_t reserved;
} rtu_mbap_event;

typedef struct {
    uint64_t frames[4];                /* by kind: request, response, exception, unknown */
    uint64_t discarded[RTU_MBAP_NERR]; /* bytes by error reason */
    uint64_t discard_events;
} rtu_mbap_counters;

/* The head of a stream: RTU_MBAP_COMPLETE, RTU_MBAP_NEED or RTU_MBAP_INVALID
 * (RTU_EINVAL for NULL pointers).  Errors are reported as soon as the bytes
 * show them (protocol id after 4 bytes, length after 6). */
int rtu_mbap_inspect(const uint8_t *data, size_t n, size_t *length, int *error);
/* RTU_KIND_* of a complete ADU for a role (RTU_ROLE_MASTER: responses). */
int rtu_mbap_kind(int role, const uint8_t *adu);
/* Header + PDU (1..253 bytes) into out; *nout = 7 + pdu_len. */
int rtu_mbap_encode(uint16_t transaction, uint8_t unit, const uint8_t *pdu, size_t pdu_len,
                    uint8_t *out, size_t cap, size_t *nout);

typedef struct {
    int role;
    int error;     /* sticky RTU_MBAP_ERR_* after a bad header: the rest is discarded */
    int eof;       /* the stream ended (rtu_mbap_framer_close) */
    size_t head;   /* first unresolved byte */
    size_t n;      /* bytes in buf */
    uint64_t base; /* stream position of buf[0] */
    rtu_mbap_counters counters;
    rtu_mbap_event event; /* the event returned by the last rtu_mbap_framer_poll */
    uint8_t buf[RTU_MBAP_FRAMER_CAP];
} rtu_mbap_framer;

int rtu_mbap_framer_init(rtu_mbap_framer *f, int role);
/* Accept bytes; returns how many were taken (offer the rest after polling).
 * After a bad header every byte is taken and counted as discarded; after
 * rtu_mbap_framer_close none is. */
size_t rtu_mbap_framer_feed(rtu_mbap_framer *f, const uint8_t *data, size_t len);
/* End of stream: an incomplete ADU becomes a truncated discard event. */
void rtu_mbap_framer_close(rtu_mbap_framer *f);
/* 1: f->event holds an event whose bytes are at rtu_mbap_framer_event_data(f)
 * until the next call; 0: nothing more until new bytes. */
int rtu_mbap_framer_poll(rtu_mbap_framer *f);
const uint8_t *rtu_mbap_framer_event_data(const rtu_mbap_framer *f);
/* Bytes still needed to complete the ADU at the head (7 when idle, 0 when an
 * event is ready or the stream is over). */
size_t rtu_mbap_framer_needed(const rtu_mbap_framer *f);

typedef struct {
    int role;
    int done;     /* a bad header or the end: the rest is one discard event */
    uint64_t pos; /* next unresolved byte */
    rtu_mbap_counters counters;
} rtu_mbap_parser;

int rtu_mbap_parser_init(rtu_mbap_parser *p, int role);
/* The ADUs of a whole capture into out (capacity cap); RTU_ENOSPC when out is
 * full (call again with a fresh out array to continue), RTU_OK when done. */
int rtu_mbap_parse(rtu_mbap_parser *p, const uint8_t *data, size_t len, rtu_mbap_event *out,
                   size_t cap, size_t *nout);

#endif /* RTU_H */
