/* libFuzzer harness for the server engine (csrc/rtu_serve_io.c): a thread that
 * answers plain reads from an image (csrc/rtu_image.c) and hands every other
 * request over as an event.
 *
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3.
 *
 * Input: byte 0 flags (bit 0: the connection defers every request; bit 1: the client shuts its end after
 * the stream; bit 2: unit 0xFF routed to the image too; bit 3: connection slot
 * 1 in place of 0; bit 4: a small send buffer on the engine's end, so that its
 * answers wait and it stops reading), byte 1 seeds the sizes of the pieces the stream is written
 * in, byte 2 seeds the image's values; then records that make the stream: a read
 * (FC 1..4, to unit 1, 0xFF or another, near the image's ranges), another
 * request (any PDU of 1..8 bytes), or raw bytes (a bad or partial header).
 *
 * The image: holding registers 0..199 plain and 200..209 held, coils 0..99,
 * input registers 5..24.  The stream goes into the client end of a socket pair
 * whose other end is attached to the serve; the harness reads what comes back,
 * takes the events and answers each REQUEST with rtu_serve_send (an empty answer
 * for some).  Checked, against this file's own framing of the stream (the MBAP
 * header rules of [TCP] 3.1.3: protocol id 0, length 2..254): each REQUEST is
 * the next request the image does not answer (rtu_image_answer on the same
 * image), in order; the bytes the client reads are, in order, the image's answer
 * ADU (the request's transaction id and unit, protocol 0, length 1 + PDU) or the
 * harness's answer, for every whole request before the end or a bad header;
 * BAD_HEADER with the header's error when the stream has one, CLOSED (err 0)
 * after a shut end when it has none, only after every REQUEST before it was
 * answered; no STALLED; the statistics count exactly the requests; nothing left
 * after the detach, and the client then sees the end of file.  The engine must
 * finish within 5 s at each step (a hang is a crash).  A violated invariant
 * aborts. */
#define _POSIX_C_SOURCE 200809L /* clock_gettime */

#include "fuzz_common.h"
#include "rtu_image.h"
#include "rtu_serve.h"

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define STREAM_CAP 4096
#define MAX_ADUS (STREAM_CAP / 8)
#define OUT_CAP (MAX_ADUS * 260)

static rtu_serve *serve;
static uint16_t hr[210], coils[100], ir[20];
static rtu_image_range hr_ranges[2], coil_ranges[1], ir_ranges[1];
static rtu_image image;
static const rtu_image *routes[256]; /* the connection's: unit 1 (and maybe 0xFF) */

static uint8_t stream[STREAM_CAP];
static uint8_t expect[OUT_CAP]; /* the bytes the client must read */
static uint8_t got[OUT_CAP + 1];
static size_t handed_off[MAX_ADUS], handed_len[MAX_ADUS];

static int64_t now_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

static size_t put_adu(uint8_t *p, unsigned tid, unsigned unit, const uint8_t *pdu, size_t n)
{
    p[0] = (uint8_t)(tid >> 8);
    p[1] = (uint8_t)tid;
    p[2] = p[3] = 0;
    p[4] = (uint8_t)((n + 1) >> 8);
    p[5] = (uint8_t)(n + 1);
    p[6] = (uint8_t)unit;
    memcpy(p + 7, pdu, n);
    return 7 + n;
}

/* The harness's answer to a handed request (len 0 for some). */
static size_t harness_answer(const uint8_t *req, uint8_t *out)
{
    uint8_t pdu[2];
    if (req[7] % 5 == 0)
        return 0;
    pdu[0] = (uint8_t)(req[7] | 0x80);
    pdu[1] = 4;
    return put_adu(out, (unsigned)req[0] << 8 | req[1], req[6], pdu, 2);
}

static void setup(void)
{
    size_t size = rtu_serve_size(2);
    serve = malloc(size);
    if (serve == NULL || rtu_serve_init(serve, 2, 1u << 20) != RTU_OK)
        FUZZ_FAIL("rtu_serve_init");
    hr_ranges[0].start = 0;
    hr_ranges[0].count = 200;
    hr_ranges[0].flags = RTU_IMAGE_PLAIN;
    hr_ranges[0].values = hr;
    hr_ranges[1].start = 200;
    hr_ranges[1].count = 10;
    hr_ranges[1].flags = RTU_IMAGE_HELD;
    hr_ranges[1].values = hr + 200;
    coil_ranges[0].start = 0;
    coil_ranges[0].count = 100;
    coil_ranges[0].flags = RTU_IMAGE_PLAIN;
    coil_ranges[0].values = coils;
    ir_ranges[0].start = 5;
    ir_ranges[0].count = 20;
    ir_ranges[0].flags = RTU_IMAGE_PLAIN;
    ir_ranges[0].values = ir;
    image.ranges[RTU_IMAGE_COILS] = coil_ranges;
    image.nranges[RTU_IMAGE_COILS] = 1;
    image.ranges[RTU_IMAGE_HOLDING_REGISTERS] = hr_ranges;
    image.nranges[RTU_IMAGE_HOLDING_REGISTERS] = 2;
    image.ranges[RTU_IMAGE_INPUT_REGISTERS] = ir_ranges;
    image.nranges[RTU_IMAGE_INPUT_REGISTERS] = 1;
}

/* The stream from the records of the input; its length. */
static size_t make_stream(fuzz_in *in)
{
    size_t n = 0;
    unsigned tid = 0;
    while (in->n > 0 && n + 16 <= STREAM_CAP) {
        const uint8_t k = fuzz_u8(in);
        uint8_t pdu[8];
        unsigned unit = (k >> 2) % 4 == 0 ? 0xFF : (k >> 2) % 4 == 1 ? fuzz_u8(in) : 1;
        switch (k & 3) {
        case 0:
        case 1: { /* a read near the ranges */
            const unsigned fc = 1 + ((k >> 4) & 3);
            const unsigned address = fuzz_u8(in);
            const unsigned quantity = (k & 0x40) ? fuzz_u16(in) : fuzz_u8(in) % 32;
            pdu[0] = (uint8_t)fc;
            pdu[1] = (uint8_t)(address >> 8);
            pdu[2] = (uint8_t)address;
            pdu[3] = (uint8_t)(quantity >> 8);
            pdu[4] = (uint8_t)quantity;
            n += put_adu(stream + n, tid++, unit, pdu, 5);
            break;
        }
        case 2: { /* any request */
            const size_t len = 1 + (k >> 5);
            size_t i;
            for (i = 0; i < len; i++)
                pdu[i] = fuzz_u8(in);
            n += put_adu(stream + n, tid++, unit, pdu, len);
            break;
        }
        default: { /* raw bytes */
            const size_t len = 1 + (k >> 5);
            size_t i;
            for (i = 0; i < len; i++)
                stream[n++] = fuzz_u8(in);
        }
        }
    }
    return n;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fuzz_in in = {data, size};
    uint8_t flags, reply[300];
    uint32_t seed, vseed, conn;
    size_t n, p = 0, nexp = 0, nhanded = 0, whole = 0, answered = 0, i;
    size_t written = 0, ngot = 0, next_handed = 0;
    int bad = 0, sv[2], terminal = 0, shut;
    rtu_serve_stats before, after;
    rtu_serve_event ev[4];
    int64_t give_up;
    if (size < 3)
        return 0;
    if (serve == NULL)
        setup();
    flags = fuzz_u8(&in);
    seed = fuzz_u8(&in);
    vseed = fuzz_u8(&in);
    shut = (flags & 2) != 0;
    conn = (flags >> 3) & 1;
    rtu_images_lock();
    for (i = 0; i < 210; i++) {
        vseed = vseed * 1103515245u + 12345u;
        hr[i] = (uint16_t)(vseed >> 8);
        if (i < 100)
            coils[i] = (uint16_t)((vseed >> 20) & 3);
        if (i < 20)
            ir[i] = (uint16_t)(vseed >> 4);
    }
    rtu_images_unlock();
    memset(routes, 0, sizeof routes);
    routes[1] = &image;
    routes[0xFF] = (flags & 4) ? &image : NULL;
    n = make_stream(&in);

    /* this file's framing of the stream, and what must come back */
    while (p < n) {
        const size_t avail = n - p;
        size_t len;
        uint8_t out[253];
        size_t out_len = 0;
        const rtu_image *img;
        if (avail >= 4 && (stream[p + 2] | stream[p + 3]) != 0) {
            bad = RTU_MBAP_ERR_PROTOCOL;
            break;
        }
        if (avail < 6)
            break;
        len = (size_t)stream[p + 4] << 8 | stream[p + 5];
        if (len < 2 || len > 254) {
            bad = RTU_MBAP_ERR_LENGTH;
            break;
        }
        if (avail < 6 + len)
            break;
        whole++;
        img = (flags & 1)                            ? NULL
              : stream[p + 6] == 1                   ? &image
              : stream[p + 6] == 0xFF && (flags & 4) ? &image
                                                     : NULL;
        if (img != NULL &&
            rtu_image_answer(img, stream + p + 7, len - 1, out, sizeof out, &out_len) == RTU_OK) {
            nexp += put_adu(expect + nexp, (unsigned)stream[p] << 8 | stream[p + 1], stream[p + 6],
                            out, out_len);
            answered++;
        } else {
            handed_off[nhanded] = p;
            handed_len[nhanded++] = 6 + len;
            nexp += harness_answer(stream + p, expect + nexp);
        }
        p += 6 + len;
    }

    if (rtu_serve_stats_get(serve, &before) != RTU_OK)
        FUZZ_FAIL("stats");
    if (socketpair(AF_UNIX, SOCK_STREAM, 0, sv) != 0)
        return 0;
    fcntl(sv[1], F_SETFL, fcntl(sv[1], F_GETFL) | O_NONBLOCK);
    if (flags & 16) { /* a small send buffer: the answers wait, the engine stops reading */
        int small = 2048;
        setsockopt(sv[0], SOL_SOCKET, SO_SNDBUF, &small, sizeof small);
    }
    if (rtu_serve_attach(serve, conn, sv[0], routes, flags & 1) != RTU_OK)
        FUZZ_FAIL("attach");
    if (rtu_serve_attach(serve, conn, sv[0], routes, 0) != RTU_EINVAL)
        FUZZ_FAIL("attached twice");

    give_up = now_ms() + 5000;
    for (;;) {
        struct pollfd pf[2];
        size_t k, taken;
        int done;
        if (written < n) {
            size_t piece;
            ssize_t w;
            seed = seed * 1103515245u + 12345u;
            piece = 1 + (seed >> 16) % 96;
            if (piece > n - written)
                piece = n - written;
            w = send(sv[1], stream + written, piece, MSG_DONTWAIT | MSG_NOSIGNAL);
            if (w > 0)
                written += (size_t)w;
            else if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)
                FUZZ_FAIL("the client's send: %d", errno);
        }
        if (written == n && shut == 1) {
            shutdown(sv[1], SHUT_WR);
            shut = 2;
        }
        for (;;) { /* what came back */
            ssize_t r = recv(sv[1], got + ngot, sizeof got - ngot, MSG_DONTWAIT);
            if (r <= 0)
                break;
            ngot += (size_t)r;
            if (ngot > nexp || memcmp(got, expect, ngot) != 0)
                FUZZ_FAIL("the client read %zu bytes, not the %zu expected (first difference "
                          "before %zu)",
                          ngot, nexp, ngot);
        }
        taken = rtu_serve_take(serve, ev, 4);
        for (k = 0; k < taken; k++) {
            if (ev[k].conn != conn)
                FUZZ_FAIL("an event of connection %u", ev[k].conn);
            if (terminal)
                FUZZ_FAIL("an event after the end");
            switch (ev[k].kind) {
            case RTU_SERVE_REQUEST: {
                size_t rl;
                if (next_handed >= nhanded || ev[k].len != handed_len[next_handed] ||
                    memcmp(ev[k].adu, stream + handed_off[next_handed], ev[k].len) != 0)
                    FUZZ_FAIL("REQUEST %zu of %zu is not the next request the image defers",
                              next_handed, nhanded);
                next_handed++;
                rl = harness_answer(ev[k].adu, reply);
                if (rtu_serve_send(serve, conn, reply, rl) != RTU_OK)
                    FUZZ_FAIL("send refused");
                if (rtu_serve_send(serve, conn, reply, rl) != RTU_EINVAL)
                    FUZZ_FAIL("a second send accepted");
                break;
            }
            case RTU_SERVE_BAD_HEADER:
                if (!bad || ev[k].err != bad || next_handed != nhanded)
                    FUZZ_FAIL("BAD_HEADER %d, the stream's %d (%zu of %zu handed)", ev[k].err, bad,
                              next_handed, nhanded);
                terminal = 1;
                break;
            case RTU_SERVE_CLOSED:
                if (bad || !shut || ev[k].err != 0 || next_handed != nhanded || written < n)
                    FUZZ_FAIL("CLOSED (err %d) where the stream %s", ev[k].err,
                              bad ? "has a bad header" : "goes on");
                terminal = 1;
                break;
            default:
                FUZZ_FAIL("event kind %d", ev[k].kind);
            }
        }
        done = (written == n || terminal) && ngot == nexp && next_handed == nhanded &&
               (terminal || (!bad && !shut));
        if (done)
            break;
        if (now_ms() > give_up)
            FUZZ_FAIL("stuck: written %zu of %zu, read %zu of %zu, handed %zu of %zu, end %d",
                      written, n, ngot, nexp, next_handed, nhanded, terminal);
        pf[0].fd = sv[1];
        pf[0].events = (short)(POLLIN | (written < n ? POLLOUT : 0));
        pf[1].fd = rtu_serve_fd(serve);
        pf[1].events = POLLIN;
        pf[0].revents = pf[1].revents = 0;
        poll(pf, 2, 100);
    }
    {
        rtu_serve_conn_state st;
        if (rtu_serve_conn(serve, conn, &st) != RTU_OK || st.handed != 0 || st.unsent != 0 ||
            st.answered != answered)
            FUZZ_FAIL("state: handed %u unsent %u answered %llu of %zu", st.handed, st.unsent,
                      (unsigned long long)st.answered, answered);
    }
    if (rtu_serve_stats_get(serve, &after) != RTU_OK)
        FUZZ_FAIL("stats");
    if (after.requests - before.requests != whole || after.answered - before.answered != answered ||
        after.handed - before.handed != nhanded)
        FUZZ_FAIL("stats: %llu requests, %llu answered, %llu handed; the stream: %zu, %zu, %zu",
                  (unsigned long long)(after.requests - before.requests),
                  (unsigned long long)(after.answered - before.answered),
                  (unsigned long long)(after.handed - before.handed), whole, answered, nhanded);
    if (rtu_serve_detach(serve, conn) != RTU_OK || rtu_serve_take(serve, ev, 4) != 0)
        FUZZ_FAIL("detach, or an event left after it");
    if (rtu_serve_detach(serve, conn) != RTU_EINVAL)
        FUZZ_FAIL("detached twice");
    {
        struct pollfd pf;
        ssize_t r;
        pf.fd = sv[1];
        pf.events = POLLIN;
        pf.revents = 0;
        if (poll(&pf, 1, 5000) != 1)
            FUZZ_FAIL("no end of file after the detach");
        r = recv(sv[1], got, sizeof got, MSG_DONTWAIT);
        /* (closed with bytes it did not read, after a bad header or before it read a
           partial request, its end resets the pair; after CLOSED it read them all) */
        if (r != 0 && !(r < 0 && errno == ECONNRESET && !(terminal && !bad)))
            FUZZ_FAIL("after the detach: recv %zd (errno %d)", r, r < 0 ? errno : 0);
    }
    close(sv[1]);
    return 0;
}
