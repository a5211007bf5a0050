/* Modbus TCP: MBAP framing of a TCP byte stream, sans-I/O.
 *
 * [TCP] 3.1.3: a Modbus TCP ADU is the 7-byte MBAP header followed by the PDU:
 *   transaction id (2 bytes), protocol id (2 bytes, 0 = MODBUS), length (2
 *   bytes: the bytes that follow, unit id + PDU), unit id (1 byte); all
 *   big-endian.  [AP] 4.1: a PDU is 1..253 bytes, so length is 2..254 and an
 *   ADU is at most 260 bytes.
 *
 * TCP gives no frame boundaries: the length field is the only delimiter.  A
 * header that breaks the rules (protocol id other than 0, length outside
 * 2..254) leaves no way to find the next ADU, so it ends the stream: the
 * framer reports one discard event for what it holds and discards the rest
 * (a server closes that connection).  Errors are found as early as the bytes
 * allow: the protocol id after 4 bytes, the length after 6.  The unit id is
 * not checked here: its meaning is the receiver's ([TCP] 3.1.3: 0xFF or
 * ignored by a plain server, the serial address behind a gateway). */
#include "rtu.h"

#include <string.h>

static unsigned rtu_be16(const uint8_t *p) { return ((unsigned)p[0] << 8) | p[1]; }

int rtu_mbap_inspect(const uint8_t *data, size_t n, size_t *length, int *error)
{
    if ((data == NULL && n > 0) || length == NULL || error == NULL) {
        return RTU_EINVAL;
    }
    *error = RTU_MBAP_ERR_NONE;
    *length = RTU_MBAP_HEADER_LEN;
    if (n >= 4 && rtu_be16(data + 2) != 0) {
        *error = RTU_MBAP_ERR_PROTOCOL; /* [TCP] 3.1.3: protocol id 0 = MODBUS */
        return RTU_MBAP_INVALID;
    }
    if (n < 6) {
        return RTU_MBAP_NEED;
    }
    const unsigned len = rtu_be16(data + 4);
    if (len < RTU_MBAP_MIN_LENGTH || len > RTU_MBAP_MAX_LENGTH) {
        *error = RTU_MBAP_ERR_LENGTH; /* unit id + a PDU of 1..253 bytes ([AP] 4.1) */
        return RTU_MBAP_INVALID;
    }
    *length = 6 + (size_t)len;
    return n >= *length ? RTU_MBAP_COMPLETE : RTU_MBAP_NEED;
}

int rtu_mbap_kind(int role, const uint8_t *adu)
{
    const int exception = (adu[7] & 0x80) != 0; /* [AP] 7: function code + 0x80 */
    switch (role) {
    case RTU_ROLE_MASTER:
        return exception ? RTU_KIND_EXCEPTION : RTU_KIND_RESPONSE;
    case RTU_ROLE_SLAVE:
        return RTU_KIND_REQUEST;
    default:
        return exception ? RTU_KIND_EXCEPTION : RTU_KIND_UNKNOWN;
    }
}

int rtu_mbap_encode(uint16_t transaction, uint8_t unit, const uint8_t *pdu, size_t pdu_len,
                    uint8_t *out, size_t cap, size_t *nout)
{
    if (pdu == NULL || out == NULL || nout == NULL || pdu_len < 1 ||
        pdu_len > RTU_MBAP_MAX_LENGTH - 1) {
        return RTU_EINVAL;
    }
    const size_t total = RTU_MBAP_HEADER_LEN + pdu_len;
    if (cap < total) {
        return RTU_ENOSPC;
    }
    const size_t len = pdu_len + 1;
    out[0] = (uint8_t)(transaction >> 8);
    out[1] = (uint8_t)(transaction & 0xFF);
    out[2] = 0;
    out[3] = 0;
    out[4] = (uint8_t)(len >> 8);
    out[5] = (uint8_t)(len & 0xFF);
    out[6] = unit;
    memmove(out + RTU_MBAP_HEADER_LEN, pdu, pdu_len);
    *nout = total;
    return RTU_OK;
}

static void rtu_mbap_count(rtu_mbap_counters *c, int kind)
{
    if (kind >= 0 && kind < 4) {
        c->frames[kind]++;
    }
}

/* ---- The incremental framer -------------------------------------------- */

int rtu_mbap_framer_init(rtu_mbap_framer *f, int role)
{
    if (f == NULL || role < RTU_ROLE_MASTER || role > RTU_ROLE_MONITOR) {
        return RTU_EINVAL;
    }
    memset(f, 0, sizeof *f);
    f->role = role;
    return RTU_OK;
}

size_t rtu_mbap_framer_feed(rtu_mbap_framer *f, const uint8_t *data, size_t len)
{
    if (f->error != RTU_MBAP_ERR_NONE) {
        /* The stream cannot be framed any more: count and drop. */
        f->counters.discarded[f->error] += len;
        return len;
    }
    if (f->eof || (data == NULL && len > 0)) {
        return 0;
    }
    if (f->head > 0) { /* forget the bytes of events already read */
        const size_t left = f->n - f->head;
        memmove(f->buf, f->buf + f->head, left);
        f->base += f->head;
        f->n = left;
        f->head = 0;
    }
    const size_t room = RTU_MBAP_FRAMER_CAP - f->n;
    const size_t take = len < room ? len : room;
    memcpy(f->buf + f->n, data, take);
    f->n += take;
    return take;
}

void rtu_mbap_framer_close(rtu_mbap_framer *f) { f->eof = 1; }

static int rtu_mbap_framer_discard(rtu_mbap_framer *f, int error)
{
    const size_t count = f->n - f->head;
    rtu_mbap_event *e = &f->event;
    e->offset = f->base + f->head;
    e->length = (uint32_t)count;
    e->kind = RTU_KIND_DISCARD;
    e->error = (uint8_t)error;
    e->reserved = 0;
    f->counters.discarded[error] += count;
    f->counters.discard_events++;
    f->head = f->n;
    return 1;
}

int rtu_mbap_framer_poll(rtu_mbap_framer *f)
{
    const size_t unresolved = f->n - f->head;
    if (unresolved == 0 || f->error != RTU_MBAP_ERR_NONE) {
        return 0;
    }
    size_t length = 0;
    int error = RTU_MBAP_ERR_NONE;
    const int st = rtu_mbap_inspect(f->buf + f->head, unresolved, &length, &error);
    if (st == RTU_MBAP_INVALID) {
        f->error = error; /* sticky: nothing after a bad header can be framed */
        return rtu_mbap_framer_discard(f, error);
    }
    if (st == RTU_MBAP_NEED) {
        return f->eof ? rtu_mbap_framer_discard(f, RTU_MBAP_ERR_TRUNCATED) : 0;
    }
    rtu_mbap_event *e = &f->event;
    e->offset = f->base + f->head;
    e->length = (uint32_t)length;
    e->kind = (uint8_t)rtu_mbap_kind(f->role, f->buf + f->head);
    e->error = RTU_MBAP_ERR_NONE;
    e->reserved = 0;
    rtu_mbap_count(&f->counters, e->kind);
    f->head += length;
    return 1;
}

const uint8_t *rtu_mbap_framer_event_data(const rtu_mbap_framer *f)
{
    return f->buf + (size_t)(f->event.offset - f->base);
}

size_t rtu_mbap_framer_needed(const rtu_mbap_framer *f)
{
    if (f->error != RTU_MBAP_ERR_NONE || f->eof) {
        return 0;
    }
    const size_t unresolved = f->n - f->head;
    size_t length = 0;
    int error = RTU_MBAP_ERR_NONE;
    const int st = rtu_mbap_inspect(f->buf + f->head, unresolved, &length, &error);
    return st == RTU_MBAP_NEED ? length - unresolved : 0;
}

/* ---- The bulk parser (a capture of one direction of a connection) ------- */

int rtu_mbap_parser_init(rtu_mbap_parser *p, int role)
{
    if (p == NULL || role < RTU_ROLE_MASTER || role > RTU_ROLE_MONITOR) {
        return RTU_EINVAL;
    }
    memset(p, 0, sizeof *p);
    p->role = role;
    return RTU_OK;
}

int rtu_mbap_parse(rtu_mbap_parser *p, const uint8_t *data, size_t len, rtu_mbap_event *out,
                   size_t cap, size_t *nout)
{
    if (p == NULL || nout == NULL || (data == NULL && len > 0) || (out == NULL && cap > 0)) {
        return RTU_EINVAL;
    }
    *nout = 0;
    while (p->pos < len && !p->done) {
        if (*nout == cap) {
            return RTU_ENOSPC;
        }
        const size_t left = len - (size_t)p->pos;
        size_t length = 0;
        int error = RTU_MBAP_ERR_NONE;
        const int st = rtu_mbap_inspect(data + p->pos, left, &length, &error);
        rtu_mbap_event *e = &out[(*nout)++];
        e->offset = p->pos;
        e->reserved = 0;
        if (st == RTU_MBAP_COMPLETE) {
            e->length = (uint32_t)length;
            e->kind = (uint8_t)rtu_mbap_kind(p->role, data + p->pos);
            e->error = RTU_MBAP_ERR_NONE;
            rtu_mbap_count(&p->counters, e->kind);
            p->pos += length;
            continue;
        }
        /* A bad header, or an ADU cut by the end of the capture: the rest. */
        if (st != RTU_MBAP_INVALID) {
            error = RTU_MBAP_ERR_TRUNCATED;
        }
        e->length = (uint32_t)left;
        e->kind = RTU_KIND_DISCARD;
        e->error = (uint8_t)error;
        p->counters.discarded[error] += left;
        p->counters.discard_events++;
        p->pos = len;
        p->done = 1;
    }
    return RTU_OK;
}
