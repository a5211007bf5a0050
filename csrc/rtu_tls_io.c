/*
 * The TLS of an mbaps:// client over OpenSSL (declared in rtu_tls.h): the
 * handshake on a connected, non-blocking socket, and the rtu_tcp_io layer the
 * Modbus TCP transaction of csrc/rtu_tcp_io.c runs through, so that an mbaps://
 * transaction is one C call with the GIL released, as a tcp:// one is.
 *
 * [SEC] MODBUS/TCP Security Protocol Specification (v36, 2021):
 *   - TLS 1.2 at least ("TLS v1.2 or newer"), never downgraded: the minimum is
 *     raised to TLS 1.2 whatever the caller asks; no renegotiation, no
 *     compression;
 *   - mutual authentication: the client's X.509v3 certificate and key are
 *     presented, the server's certificate must chain to the client's trusted
 *     CA (SSL_VERIFY_PEER) and name the host dialled (SSL_set1_host: DNS names,
 *     or IP addresses for an address);
 *   - session resumption (reconnects without a full handshake): the latest
 *     session the server gave is kept (the new-session callback: TLS 1.3 sends
 *     its tickets after the handshake) for the caller to resume.
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b: the MBAP ADUs
 * are the application data of the TLS records; the transaction itself (build,
 * send, wait with the deadline, read the answer whole by its length field, judge
 * it) is rtu_tcp_io.c's.
 *
 * Waits: the socket is non-blocking; SSL_ERROR_WANT_READ / WANT_WRITE become a
 * poll for POLLIN / POLLOUT until the deadline (a TLS read may need to write and
 * a write to read).  A signal (EINTR) ends the handshake's wait early
 * (RTU_TLS_INTERRUPTED) so that Python runs its handler.
 */
#if defined(__linux__)
#define _GNU_SOURCE /* ppoll */
#elif !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L
#endif

#include "rtu.h"
#include "rtu_clock.h"
#include "rtu_tls.h"

#include <errno.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <openssl/err.h>
#include <openssl/ssl.h>
#include <openssl/x509v3.h>

struct rtu_tls_ctx {
    SSL_CTX *ctx;
};

struct rtu_tls_conn {
    rtu_tcp_io io; /* first: the transaction's layer is the connection */
    SSL *ssl;
    int fd;
    int done;            /* the handshake is over */
    int broken;          /* a fatal TLS error: no close_notify at the end */
    int err;             /* errno of RTU_TLS_ERRNO */
    SSL_SESSION *latest; /* the latest resumable session the server gave */
    char message[256];
};

/* OpenSSL's error queue, its first reason, into buf (and the queue emptied) */
static void take_errors(char *buf, size_t len, const char *fallback)
{
    unsigned long e = ERR_get_error();
    const char *reason = e != 0 ? ERR_reason_error_string(e) : NULL;
    if (reason != NULL)
        snprintf(buf, len, "%s", reason);
    else if (e != 0)
        ERR_error_string_n(e, buf, len);
    else
        snprintf(buf, len, "%s", fallback);
    ERR_clear_error();
}

/* ---- the context ---- */

static int new_session(SSL *ssl, SSL_SESSION *session)
{
    rtu_tls_conn *c = SSL_get_app_data(ssl);
    if (c == NULL || !SSL_SESSION_is_resumable(session))
        return 0; /* not kept: OpenSSL frees it */
    SSL_SESSION_free(c->latest);
    c->latest = session; /* the reference OpenSSL passed is ours (returning 1) */
    return 1;
}

static int refused(SSL_CTX *ctx, char *err, size_t errlen, const char *what, const char *path)
{
    char reason[160];
    take_errors(reason, sizeof reason, "cannot be read");
    if (err != NULL && errlen > 0)
        snprintf(err, errlen, "%s %s: %s", what, path, reason);
    SSL_CTX_free(ctx);
    return RTU_EINVAL;
}

int rtu_tls_ctx_new(rtu_tls_ctx **out, const char *cert, const char *key, const char *ca,
                    int min_version, int max_version, char *err, size_t errlen)
{
    SSL_CTX *ctx;
    rtu_tls_ctx *t;
    uint64_t options = SSL_OP_NO_RENEGOTIATION | SSL_OP_NO_COMPRESSION;
    if (out == NULL || cert == NULL || key == NULL || ca == NULL || min_version < 0 ||
        max_version < 0 || (max_version != 0 && max_version < RTU_TLS_V1_2))
        return RTU_EINVAL;
    *out = NULL;
    ERR_clear_error();
    ctx = SSL_CTX_new(TLS_client_method());
    if (ctx == NULL)
        return RTU_ENOSPC;
    /* [SEC]: TLS 1.2 or later, whatever was asked */
    if (min_version < RTU_TLS_V1_2)
        min_version = RTU_TLS_V1_2;
    if (!SSL_CTX_set_min_proto_version(ctx, min_version) ||
        !SSL_CTX_set_max_proto_version(ctx, max_version))
        return refused(ctx, err, errlen, "version", "range");
    /* a peer closing without close_notify is an end of the stream (as Python's
     * ssl sockets read it: suppress_ragged_eofs); the MBAP length field, not the
     * stream's end, delimits every answer, so nothing is truncated unseen */
    options |= SSL_OP_IGNORE_UNEXPECTED_EOF;
    SSL_CTX_set_options(ctx, options);
    SSL_CTX_set_verify(ctx, SSL_VERIFY_PEER, NULL);
    /* one read() per record or more, not two (header, then body): the bytes read
     * beyond a record wait in the read-ahead buffer (tls_pending says so) */
    SSL_CTX_set_read_ahead(ctx, 1);
    if (SSL_CTX_use_certificate_chain_file(ctx, cert) != 1)
        return refused(ctx, err, errlen, "cert", cert);
    if (SSL_CTX_use_PrivateKey_file(ctx, key, SSL_FILETYPE_PEM) != 1)
        return refused(ctx, err, errlen, "key", key);
    if (SSL_CTX_check_private_key(ctx) != 1)
        return refused(ctx, err, errlen, "key", key);
    if (SSL_CTX_load_verify_locations(ctx, ca, NULL) != 1)
        return refused(ctx, err, errlen, "ca", ca);
    /* the sessions go to the connection (the caller keeps them per server),
     * not to OpenSSL's cache */
    SSL_CTX_set_session_cache_mode(ctx, SSL_SESS_CACHE_CLIENT | SSL_SESS_CACHE_NO_INTERNAL_STORE);
    SSL_CTX_sess_set_new_cb(ctx, new_session);
    t = malloc(sizeof *t);
    if (t == NULL) {
        SSL_CTX_free(ctx);
        return RTU_ENOSPC;
    }
    t->ctx = ctx;
    *out = t;
    return RTU_OK;
}

void rtu_tls_ctx_free(rtu_tls_ctx *t)
{
    if (t == NULL)
        return;
    SSL_CTX_free(t->ctx);
    free(t);
}

/* ---- the layer of the transaction (rtu_tcp_io) ---- */

/* One SSL_write/SSL_read's outcome in rtu_tcp_io's terms (see rtu_tcp.h) */
static ptrdiff_t outcome(rtu_tls_conn *c, int ok, size_t moved, short *want)
{
    int e;
    if (ok > 0)
        return (ptrdiff_t)moved;
    e = SSL_get_error(c->ssl, ok);
    switch (e) {
    case SSL_ERROR_WANT_READ:
        *want = POLLIN;
        errno = EAGAIN;
        return -1;
    case SSL_ERROR_WANT_WRITE:
        *want = POLLOUT;
        errno = EAGAIN;
        return -1;
    case SSL_ERROR_ZERO_RETURN: /* close_notify: the server closed */
        return 0;
    case SSL_ERROR_SYSCALL:
        c->broken = 1;
        if (errno == 0) /* an end of file (OpenSSL 3 without the option above) */
            return 0;
        ERR_clear_error();
        return -1; /* errno: the system's */
    default:
        c->broken = 1;
        take_errors(c->message, sizeof c->message, "TLS error");
        errno = EPROTO;
        return -1;
    }
}

static ptrdiff_t tls_send(rtu_tcp_io *io, const uint8_t *data, size_t len, short *want)
{
    rtu_tls_conn *c = (rtu_tls_conn *)io;
    size_t moved = 0;
    int ok;
    ERR_clear_error();
    errno = 0;
    c->message[0] = '\0'; /* (this call's words only: rtu_tls_conn_message) */
    ok = SSL_write_ex(c->ssl, data, len, &moved);
    return outcome(c, ok, moved, want);
}

static ptrdiff_t tls_recv(rtu_tcp_io *io, uint8_t *data, size_t len, short *want)
{
    rtu_tls_conn *c = (rtu_tls_conn *)io;
    size_t moved = 0;
    int ok;
    ERR_clear_error();
    errno = 0;
    c->message[0] = '\0'; /* (this call's words only: rtu_tls_conn_message) */
    ok = SSL_read_ex(c->ssl, data, len, &moved);
    return outcome(c, ok, moved, want);
}

/* bytes read from the socket but not returned yet: decrypted (SSL_pending) or
 * still in the read-ahead buffer (SSL_has_pending): poll would not see them */
static size_t tls_pending(rtu_tcp_io *io)
{
    SSL *ssl = ((rtu_tls_conn *)io)->ssl;
    int n = SSL_pending(ssl);
    return n > 0 ? (size_t)n : (size_t)SSL_has_pending(ssl);
}

/* ---- the connection ---- */

int rtu_tls_conn_new(rtu_tls_conn **out, rtu_tls_ctx *t, int fd, const char *host,
                     rtu_tls_session *session)
{
    rtu_tls_conn *c;
    if (out == NULL || t == NULL || fd < 0 || host == NULL || host[0] == '\0')
        return RTU_EINVAL;
    *out = NULL;
    c = calloc(1, sizeof *c);
    if (c == NULL)
        return RTU_ENOSPC;
    c->io.send = tls_send;
    c->io.recv = tls_recv;
    c->io.pending = tls_pending;
    c->fd = fd;
    ERR_clear_error();
    c->ssl = SSL_new(t->ctx);
    if (c->ssl == NULL || !SSL_set_fd(c->ssl, fd) || !SSL_set_app_data(c->ssl, c)) {
        rtu_tls_conn_free(c);
        return RTU_ENOSPC;
    }
    /* [SEC]: the server's certificate names the host dialled: an IP address
     * is checked against the certificate's IP addresses, a name against its DNS
     * names (SSL_set1_host); SNI only for a name (RFC 6066 3) */
    {
        ASN1_OCTET_STRING *ip = a2i_IPADDRESS(host);
        int ok;
        if (ip != NULL)
            ok = X509_VERIFY_PARAM_set1_ip(SSL_get0_param(c->ssl), ASN1_STRING_get0_data(ip),
                                           (size_t)ASN1_STRING_length(ip));
        else
            ok = SSL_set1_host(c->ssl, host) && SSL_set_tlsext_host_name(c->ssl, host);
        ASN1_OCTET_STRING_free(ip);
        if (!ok) {
            rtu_tls_conn_free(c);
            ERR_clear_error();
            return RTU_EINVAL;
        }
    }
    if (session != NULL && !SSL_set_session(c->ssl, (SSL_SESSION *)session)) {
        rtu_tls_conn_free(c);
        ERR_clear_error();
        return RTU_EINVAL;
    }
    *out = c;
    return RTU_OK;
}

int rtu_tls_handshake(rtu_tls_conn *c, int64_t timeout_ns)
{
    int64_t deadline;
    if (c == NULL || c->ssl == NULL || timeout_ns < 0)
        return RTU_EINVAL;
    if (c->done)
        return RTU_TLS_DONE;
    deadline = rtu_now_ns() + timeout_ns;
    for (;;) {
        int r, e;
        short want;
        ERR_clear_error();
        errno = 0;
        r = SSL_connect(c->ssl);
        if (r == 1) {
            c->done = 1;
            return RTU_TLS_DONE;
        }
        e = SSL_get_error(c->ssl, r);
        if (e == SSL_ERROR_WANT_READ)
            want = POLLIN;
        else if (e == SSL_ERROR_WANT_WRITE)
            want = POLLOUT;
        else {
            long verify = SSL_get_verify_result(c->ssl);
            c->broken = 1;
            if (verify != X509_V_OK) {
                /* the server's certificate refused: the verify error's words
                 * (as Python's ssl reports it: "certificate has expired"...) */
                snprintf(c->message, sizeof c->message, "%s",
                         X509_verify_cert_error_string(verify));
                ERR_clear_error();
                return RTU_TLS_VERIFY;
            }
            if (e == SSL_ERROR_SYSCALL && ERR_peek_error() == 0) {
                if (errno == 0) {
                    snprintf(c->message, sizeof c->message, "the server closed the connection");
                    return RTU_TLS_CLOSED;
                }
                c->err = errno;
                snprintf(c->message, sizeof c->message, "%s", strerror(errno));
                return RTU_TLS_ERRNO;
            }
            if (e == SSL_ERROR_ZERO_RETURN) {
                snprintf(c->message, sizeof c->message, "the server closed the connection");
                return RTU_TLS_CLOSED;
            }
            take_errors(c->message, sizeof c->message, "handshake failed");
            return RTU_TLS_FAILED;
        }
        r = rtu_wait_fd(c->fd, want, deadline);
        if (r < 0) {
            if (errno == EINTR)
                return RTU_TLS_INTERRUPTED;
            c->err = errno;
            c->broken = 1;
            snprintf(c->message, sizeof c->message, "%s", strerror(errno));
            return RTU_TLS_ERRNO;
        }
        if (r == 0) {
            c->broken = 1; /* a handshake half done: no close_notify */
            snprintf(c->message, sizeof c->message, "timed out");
            return RTU_TLS_TIMEOUT;
        }
    }
}

const char *rtu_tls_conn_message(rtu_tls_conn *c) { return c == NULL ? "" : c->message; }

int rtu_tls_conn_errno(rtu_tls_conn *c) { return c == NULL ? 0 : c->err; }

int rtu_tls_conn_reused(rtu_tls_conn *c)
{
    return c != NULL && c->done && SSL_session_reused(c->ssl) ? 1 : 0;
}

int rtu_tls_conn_version(rtu_tls_conn *c) { return c != NULL && c->done ? SSL_version(c->ssl) : 0; }

rtu_tcp_io *rtu_tls_conn_io(rtu_tls_conn *c) { return c == NULL ? NULL : &c->io; }

rtu_tls_session *rtu_tls_conn_session(rtu_tls_conn *c)
{
    if (c == NULL || c->latest == NULL || !SSL_SESSION_up_ref(c->latest))
        return NULL;
    return (rtu_tls_session *)c->latest;
}

void rtu_tls_session_free(rtu_tls_session *s) { SSL_SESSION_free((SSL_SESSION *)s); }

void rtu_tls_close_notify(rtu_tls_conn *c)
{
    if (c == NULL || c->ssl == NULL || !c->done)
        return;
    if (c->broken) {
        /* The connection ended without a closure alert (reset, a broken pipe, the
         * server gone): its session stays resumable.  RFC 5246 7.2.1: "as of TLS
         * 1.1, failure to properly close a connection no longer requires that a
         * session not be resumed"; RFC 8446 ties no session to the closure.  A fatal
         * alert (sent or received) has made the session non-resumable already
         * (SSL_CTX_remove_session); without this mark SSL_free would do the same to
         * every session whose connection did not send close_notify. */
        SSL_set_shutdown(c->ssl, SSL_get_shutdown(c->ssl) | SSL_SENT_SHUTDOWN);
        return;
    }
    /* once, without waiting for the server's (the socket is non-blocking) */
    ERR_clear_error();
    (void)SSL_shutdown(c->ssl);
    ERR_clear_error();
    c->broken = 1; /* nothing more is sent */
}

void rtu_tls_conn_free(rtu_tls_conn *c)
{
    if (c == NULL)
        return;
    SSL_free(c->ssl); /* (no I/O: the socket may be closed by now) */
    SSL_SESSION_free(c->latest);
    free(c);
}
