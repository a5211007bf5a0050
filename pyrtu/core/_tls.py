"""The TLS of an ``mbaps://`` client in the C core (csrc/rtu_tls_io.c over the system's
OpenSSL), and the client context that makes it possible.

MODBUS/TCP Security (v36, 2021) asks for TLS 1.2 or later, the client's X.509v3
certificate presented, the server's verified against the client's CA, and session
resumption.  Python's `ssl.SSLContext` does not say which files it was made from, so
the C core cannot build its OpenSSL context from one: `FileContext` is the
`ssl.SSLContext` that remembers them (``pyrtu.security.tls.client_context`` makes
one).  `accelerator` decides, once per connect, whether the C path runs it:

- the C core is the backend (not ``backend="python"``), built with its POSIX I/O and
  with OpenSSL (pyrtu/core/_build_core.py: ``pkg-config openssl``);
- the context is a `FileContext` whose verification is still MODBUS/TCP Security's
  (``verify_mode`` CERT_REQUIRED, ``check_hostname`` True): a context made or changed
  otherwise keeps Python's ssl module, which honours every setting it has
  (its minimum and maximum versions are mirrored: TLS 1.2 at least either way).

Otherwise the caller (pyrtu/tcp/client.py) runs the Python ssl path (pyrtu/tcp/tls.py).
A C connection's transaction is the tcp:// one (csrc/rtu_tcp_io.c, the GIL released)
through the connection's `CTlsConnection.io` layer.
"""

from __future__ import annotations

import contextlib
import contextvars
import ssl
import weakref
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

#: the protocol version numbers of C's RTU_TLS_V1_* (as ssl.TLSVersion has them)
_VERSIONS = {ssl.TLSVersion.TLSv1_2: 0x0303, ssl.TLSVersion.TLSv1_3: 0x0304}


#: the TLS session for the connect under way in this task (`resuming`)
_RESUME: contextvars.ContextVar[ssl.SSLSession | None] = contextvars.ContextVar(
    "pyrtu_tls_resume", default=None
)


@contextlib.contextmanager
def resuming(session: ssl.SSLSession | None) -> Iterator[None]:
    """Within the block, a `FileContext`'s client connection made in this task (or
    thread) resumes ``session``: asyncio's ``create_connection`` takes no session,
    and calls the context's ``wrap_bio`` in the task that awaits it."""
    token = _RESUME.set(session)
    try:
        yield
    finally:
        _RESUME.reset(token)


class FileContext(ssl.SSLContext):
    """An `ssl.SSLContext` that remembers the PEM files of its certificate, key and CA,
    so that the C core can make its own OpenSSL context from the same files; its
    client connections over memory BIOs (asyncio's) resume the session `resuming`
    names."""

    cert_file: str
    key_file: str
    ca_file: str

    def remember_files(self, cert: str | Path, key: str | Path, ca: str | Path) -> None:
        self.cert_file, self.key_file, self.ca_file = str(cert), str(key), str(ca)

    def wrap_bio(
        self,
        incoming: ssl.MemoryBIO,
        outgoing: ssl.MemoryBIO,
        server_side: bool = False,
        server_hostname: str | bytes | None = None,
        session: ssl.SSLSession | None = None,
    ) -> ssl.SSLObject:
        if session is None and not server_side:
            session = _RESUME.get()
        return super().wrap_bio(incoming, outgoing, server_side, server_hostname, session)


class CTlsError(OSError):
    """A handshake of the C path that failed, in the terms of Python's ssl errors'
    attributes (``kind``: ``"verify"``, ``"failed"``, ``"closed"``; ``message``:
    OpenSSL's words), so that the connect error says it as the Python path does."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message


def _lib(backend: ModuleType) -> Any:
    """The C core's lib when ``backend`` is it and it has the TLS part, else None."""
    if getattr(backend, "BACKEND", "python") != "c" or not getattr(backend, "POSIX_IO", False):
        return None
    lib = backend.lib
    return lib if hasattr(lib, "rtu_tls_ctx_new") else None


def available(backend: ModuleType) -> bool:
    """Whether ``backend`` runs ``mbaps://`` in C (its TLS part built)."""
    return _lib(backend) is not None


class CTlsContext:
    """The C core's OpenSSL context of one `FileContext` (its files, versions and
    as they were when made) and the sessions to resume, per (host, port)."""

    def __init__(self, backend: ModuleType, context: FileContext, key: tuple[int, int]) -> None:
        self._ffi, self._lib = backend.ffi, backend.lib
        ffi, lib = self._ffi, self._lib
        self.key = key
        out = ffi.new("rtu_tls_ctx **")
        err = ffi.new("char[]", 512)
        files = [f.encode() for f in (context.cert_file, context.key_file, context.ca_file)]
        rc = lib.rtu_tls_ctx_new(out, *files, *key, err, 512)
        if rc != lib.RTU_OK:
            raise CTlsError("failed", ffi.string(err).decode(errors="replace") or f"code {rc}")
        self._ctx = ffi.gc(out[0], lib.rtu_tls_ctx_free)
        self.sessions: dict[tuple[str, int], Any] = {}

    def connect(self, fd: int, host: str, port: int, timeout: float) -> CTlsConnection:
        """The handshake on the connected, non-blocking socket ``fd`` (resuming the
        session of the last connection to ``host:port``) within ``timeout`` seconds;
        `CTlsError`, `TimeoutError` or `OSError` when it fails."""
        return CTlsConnection(self, fd, host, port, timeout)

    def keep(self, host: str, port: int, conn: CTlsConnection) -> None:
        """Keep ``conn``'s latest session for the next connection to ``host:port``."""
        session = self._lib.rtu_tls_conn_session(conn.conn)
        if session != self._ffi.NULL:
            self.sessions[(host, port)] = self._ffi.gc(session, self._lib.rtu_tls_session_free)


class CTlsConnection:
    """One TLS connection of the C path on a socket (the caller's: it closes it after
    `close`): ``io``, the layer its transactions run through (rtu_tcp_xfer's io)."""

    def __init__(self, owner: CTlsContext, fd: int, host: str, port: int, timeout: float) -> None:
        ffi, lib = owner._ffi, owner._lib
        self._lib = lib
        out = ffi.new("rtu_tls_conn **")
        session = owner.sessions.get((host, port), ffi.NULL)
        rc = lib.rtu_tls_conn_new(out, owner._ctx, fd, host.encode(), session)
        if rc != lib.RTU_OK:
            raise CTlsError("failed", f"cannot set up a TLS connection to {host} (code {rc})")
        # freed when collected too (an unclosed client): rtu_tls_conn_free does no I/O
        self.conn = ffi.gc(out[0], lib.rtu_tls_conn_free)
        self._ffi = ffi
        try:
            status = lib.rtu_tls_handshake(self.conn, int(timeout * 1e9))
            while status == lib.RTU_TLS_INTERRUPTED:  # a signal's handler ran (or raised)
                status = lib.rtu_tls_handshake(self.conn, int(timeout * 1e9))
            if status != lib.RTU_TLS_DONE:
                message = self.message()
                if status == lib.RTU_TLS_TIMEOUT:
                    raise TimeoutError(message)
                if status == lib.RTU_TLS_ERRNO:
                    raise OSError(lib.rtu_tls_conn_errno(self.conn), message)
                kind = {lib.RTU_TLS_VERIFY: "verify", lib.RTU_TLS_CLOSED: "closed"}
                raise CTlsError(kind.get(status, "failed"), message)
        except BaseException:
            self.close()
            raise
        owner.keep(host, port, self)  # (TLS 1.2: the session is there now)
        self.io = lib.rtu_tls_conn_io(self.conn)
        self.version = {0x0303: "TLSv1.2", 0x0304: "TLSv1.3"}.get(
            lib.rtu_tls_conn_version(self.conn), ""
        )

    def message(self) -> str:
        """OpenSSL's words for the connection's last error (empty: none of its own)."""
        if self.conn is None:
            return ""
        text: bytes = self._ffi.string(self._lib.rtu_tls_conn_message(self.conn))
        return text.decode(errors="replace")

    @property
    def reused(self) -> bool:
        """Whether the handshake resumed a session (SSL_session_reused)."""
        return bool(self._lib.rtu_tls_conn_reused(self.conn))

    def close(self) -> None:
        """close_notify (when the connection is sound; the socket still open) and the
        connection freed."""
        conn, self.conn = self.conn, None
        if conn is not None:
            self._lib.rtu_tls_close_notify(conn)
            self._ffi.release(conn)  # (rtu_tls_conn_free now)


_contexts: weakref.WeakKeyDictionary[FileContext, CTlsContext] = weakref.WeakKeyDictionary()


def accelerator(context: ssl.SSLContext, backend: ModuleType) -> CTlsContext | None:
    """The C context that runs ``context`` on ``backend``, None when the Python ssl path
    must (see the module doc); made once per context (again if its versions changed)."""
    if (
        not isinstance(context, FileContext)
        or context.verify_mode != ssl.CERT_REQUIRED
        or not context.check_hostname
        or context.maximum_version not in (*_VERSIONS, ssl.TLSVersion.MAXIMUM_SUPPORTED)
        or _lib(backend) is None
    ):
        return None
    key = (  # (a minimum below TLS 1.2 is raised to it in C: never downgraded)
        _VERSIONS.get(context.minimum_version, 0),
        _VERSIONS.get(context.maximum_version, 0),
    )
    made = _contexts.get(context)
    if made is None or made.key != key:
        made = _contexts[context] = CTlsContext(backend, context, key)
    return made


def forget_sessions(context: ssl.SSLContext) -> None:
    """The C path's sessions of ``context`` forgotten (the next connects run a full
    handshake)."""
    made = _contexts.get(context) if isinstance(context, FileContext) else None
    if made is not None:
        made.sessions.clear()


__all__ = [
    "CTlsConnection",
    "CTlsContext",
    "CTlsError",
    "FileContext",
    "accelerator",
    "available",
    "forget_sessions",
    "resuming",
]
