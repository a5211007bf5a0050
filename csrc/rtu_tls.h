/*
 * pyrtu C core: the TLS of an mbaps:// client (MODBUS/TCP Security), over the
 * system's OpenSSL (csrc/rtu_tls_io.c; compiled only where OpenSSL's headers
 * are found: pyrtu/core/_build_core.py), so that the sync master's mbaps://
 * transaction is one C call with the GIL released, as a tcp:// one is
 * (csrc/rtu_tcp_io.c, through the rtu_tcp_io layer of rtu_tcp.h).
 *
 * [SEC] MODBUS/TCP Security Protocol Specification (v36, 2021): TLS 1.2 or
 *       later (never less), mutual authentication with X.509v3 certificates,
 *       the server's certificate verified against the client's trusted CA,
 *       session resumption to make reconnects cheap.
 * [TCP] MODBUS Messaging on TCP/IP Implementation Guide V1.0b: the
 *       transaction run over the TLS connection is the one of rtu_tcp.h.
 *
 * Objects (all opaque; each freed by its own rtu_tls_*_free, which takes NULL):
 *   - rtu_tls_ctx: the client's certificate, key and trusted CA, and the
 *     versions allowed (the OpenSSL SSL_CTX), one per client context;
 *   - rtu_tls_conn: one TLS connection on a connected socket (the caller's:
 *     never closed here), its handshake, and the rtu_tcp_io the transaction
 *     runs through (rtu_tls_conn_io);
 *   - rtu_tls_session: a session to resume at the next connect (the latest
 *     the server gave: TLS 1.3 sends its tickets after the handshake).
 */
#ifndef RTU_TLS_H
#define RTU_TLS_H

#include <stddef.h>
#include <stdint.h>

#include "rtu_tcp.h"

typedef struct rtu_tls_ctx rtu_tls_ctx;
typedef struct rtu_tls_conn rtu_tls_conn;
typedef struct rtu_tls_session rtu_tls_session;

/* rtu_tls_handshake's results */
#define RTU_TLS_DONE 0    /* the connection is up (rtu_tls_conn_reused: resumed?) */
#define RTU_TLS_TIMEOUT 1 /* the deadline came first */
#define RTU_TLS_VERIFY 2  /* the server's certificate or name refused (message) */
#define RTU_TLS_FAILED \
    3                         /* the handshake failed otherwise: an alert, a protocol
                                 version refused, not TLS at all (message) */
#define RTU_TLS_CLOSED 4      /* the server closed the connection during it */
#define RTU_TLS_ERRNO 5       /* a system call failed (rtu_tls_conn_errno) */
#define RTU_TLS_INTERRUPTED 6 /* a signal: call again to go on */

/* The protocol versions (TLS's own numbers, as OpenSSL and Python's
 * ssl.TLSVersion have them) */
#define RTU_TLS_V1_2 0x0303
#define RTU_TLS_V1_3 0x0304

/* A client context from PEM files: its certificate chain and key, the CA
 * (file) the server's certificate must chain to; versions min_version..max_version
 * (0: no maximum; a minimum below TLS 1.2 is raised to it: [SEC] refuses
 * TLS 1.0/1.1); no renegotiation, no compression.  RTU_OK, RTU_EINVAL (a file
 * refused: err says which and why), RTU_ENOSPC (out of memory). */
int rtu_tls_ctx_new(rtu_tls_ctx **out, const char *cert, const char *key, const char *ca,
                    int min_version, int max_version, char *err, size_t errlen);
void rtu_tls_ctx_free(rtu_tls_ctx *ctx);

/* A connection on the connected, non-blocking socket fd to `host`
 * (a name, checked against the certificate's DNS names and sent as SNI, or an
 * IP address, checked against its IP addresses), resuming `session` (NULL:
 * none; not taken: the caller still frees it).  RTU_OK, RTU_EINVAL, RTU_ENOSPC. */
int rtu_tls_conn_new(rtu_tls_conn **out, rtu_tls_ctx *ctx, int fd, const char *host,
                     rtu_tls_session *session);
/* Frees c without any I/O (the socket may be closed, its number another file's) */
void rtu_tls_conn_free(rtu_tls_conn *c);
/* Sends close_notify ([SEC]: a TLS closure alert before the TCP close) once,
 * not waiting for the server's; nothing after a handshake not done.  On a
 * connection that broke (no alert can go) it marks the closure done instead, so
 * that the session stays resumable (RFC 5246 7.2.1); a fatal TLS alert has made
 * it non-resumable already.  Call it while the socket is open, before
 * rtu_tls_conn_free. */
void rtu_tls_close_notify(rtu_tls_conn *c);

/* Run (or go on with, after RTU_TLS_INTERRUPTED) the handshake until done or
 * `timeout_ns` after this call: RTU_TLS_*, or RTU_EINVAL. */
int rtu_tls_handshake(rtu_tls_conn *c, int64_t timeout_ns);
/* What went wrong (RTU_TLS_VERIFY, RTU_TLS_FAILED, an EPROTO of the transaction):
 * OpenSSL's words ("certificate has expired", "unsupported protocol"...). */
const char *rtu_tls_conn_message(rtu_tls_conn *c);
int rtu_tls_conn_errno(rtu_tls_conn *c);
/* 1 when the handshake resumed a session (SSL_session_reused), else 0 */
int rtu_tls_conn_reused(rtu_tls_conn *c);
/* the version negotiated: RTU_TLS_V1_2, RTU_TLS_V1_3 (0 before the handshake) */
int rtu_tls_conn_version(rtu_tls_conn *c);
/* The layer the transaction runs through (x->io of rtu_tcp_xfer): TLS records
 * on the socket; a TLS error is errno EPROTO (message: rtu_tls_conn_message). */
rtu_tcp_io *rtu_tls_conn_io(rtu_tls_conn *c);
/* The latest resumable session the server gave on this connection (a new
 * reference: rtu_tls_session_free), NULL if none. */
rtu_tls_session *rtu_tls_conn_session(rtu_tls_conn *c);
void rtu_tls_session_free(rtu_tls_session *s);

#endif
