"""MODBUS/TCP Security's TLS: the contexts of a listener and of an ``mbaps://`` client,
and the client's role read from its certificate.

The specification (v36, 2021): TLS 1.2 or later, mutual authentication with X.509v3
certificates, the port 802, the client's role in the certificate extension
1.3.6.1.4.1.50316.802.1, an ASN.1 UTF8String.  A listener requires a client
certificate signed by its CA (``--tls-ca``), refuses TLS 1.0 and 1.1, and never
renegotiates; the role is read with the ``cryptography`` package
(``pip install 'pyrtu[tls]'``).  A certificate without the extension (or whose value
is no UTF8String) has no role: only rules by client address can let it in.

Every error names the option it comes from (``--tls-cert`` ...), as the CLI shows it;
in Python the keywords are the same words (``cert``, ``key``, ``ca``).
"""

from __future__ import annotations

import ssl
from dataclasses import dataclass
from pathlib import Path

from pyrtu.core._tls import FileContext

from .policy import Identity

#: the role extension of MODBUS/TCP Security
ROLE_OID = "1.3.6.1.4.1.50316.802.1"
#: the port of Modbus/TCP Security (IANA "mbap-s")
MBAPS_PORT = 802
_UTF8STRING = 0x0C


class TlsSetupError(ValueError):
    """A certificate, key or CA file that cannot be used (the message names it;
    ``option`` is which of the three: ``"cert"``, ``"key"`` or ``"ca"``)."""

    def __init__(self, message: str, option: str = "") -> None:
        super().__init__(message)
        self.option = option


def _check_file(prefix: str, option: str, path: str | Path) -> str:
    p = Path(path)
    if not p.is_file():
        raise TlsSetupError(f"{prefix}{option} {path}: no such file", option)
    return str(p)


def _check_certificate(prefix: str, path: str) -> None:
    """TlsSetupError unless ``path`` holds a PEM certificate (loaded as OpenSSL loads
    a CA file: any certificate in it counts)."""
    scratch = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    try:
        scratch.load_verify_locations(cafile=path)
    except (ssl.SSLError, OSError) as exc:
        message = f"{prefix}cert {path}: not a certificate (PEM): {exc}"
        raise TlsSetupError(message, "cert") from None


def _context(
    purpose: ssl.Purpose, cert: str | Path, key: str | Path, ca: str | Path, prefix: str
) -> ssl.SSLContext:
    side = (
        ssl.PROTOCOL_TLS_SERVER if purpose is ssl.Purpose.CLIENT_AUTH else ssl.PROTOCOL_TLS_CLIENT
    )
    context = FileContext(side) if purpose is ssl.Purpose.SERVER_AUTH else ssl.SSLContext(side)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.options |= ssl.OP_NO_RENEGOTIATION | ssl.OP_NO_COMPRESSION
    context.verify_mode = ssl.CERT_REQUIRED
    cert_file = _check_file(prefix, "cert", cert)
    key_file = _check_file(prefix, "key", key)
    ca_file = _check_file(prefix, "ca", ca)
    _check_certificate(prefix, cert_file)
    try:
        context.load_cert_chain(cert_file, key_file)
    except (ssl.SSLError, OSError) as exc:  # the certificate is one: its key is not
        raise TlsSetupError(
            f"{prefix}cert {cert} / {prefix}key {key}: not a certificate and its key "
            f"(PEM): {exc.strerror or exc}",
            "key",
        ) from None
    try:
        context.load_verify_locations(cafile=ca_file)
    except (ssl.SSLError, OSError) as exc:
        raise TlsSetupError(f"{prefix}ca {ca}: not a CA certificate (PEM): {exc}", "ca") from None
    if isinstance(context, FileContext):
        context.remember_files(cert_file, key_file, ca_file)
    return context


def server_context(cert: str | Path, key: str | Path, ca: str | Path) -> ssl.SSLContext:
    """The context of a TLS listener: its certificate and key, the CA its clients'
    certificates must be signed by (required), TLS 1.2 minimum, no renegotiation."""
    return _context(ssl.Purpose.CLIENT_AUTH, cert, key, ca, "--tls-")


def client_context(cert: str | Path, key: str | Path, ca: str | Path) -> ssl.SSLContext:
    """The context of an ``mbaps://`` client: its certificate and key, the CA the
    server's certificate must be signed by; the server's host name is checked.  The
    sync client runs it in C (pyrtu/core/_tls.py) where the C core has OpenSSL."""
    context = _context(ssl.Purpose.SERVER_AUTH, cert, key, ca, "--tls-")
    context.check_hostname = True
    return context


def _utf8string(value: bytes) -> str | None:
    """The text of a DER UTF8String, None if ``value`` is not one."""
    if len(value) < 2 or value[0] != _UTF8STRING:
        return None
    length, at = value[1], 2
    if length & 0x80:
        size = length & 0x7F
        if not 1 <= size <= 4 or len(value) < 2 + size:
            return None
        length, at = int.from_bytes(value[2 : 2 + size], "big"), 2 + size
    if len(value) != at + length:
        return None
    try:
        return value[at:].decode("utf-8")
    except UnicodeDecodeError:
        return None


def certificate_role(der: bytes) -> tuple[str | None, str]:
    """(role, subject) of a DER certificate: the role extension's UTF8String (None
    when absent or not a UTF8String) and the subject as RFC 4514 text."""
    try:
        from cryptography import x509
    except ImportError:  # pragma: no cover - the tests install it
        raise TlsSetupError(
            "TLS listeners read the client's role with the cryptography package: "
            "pip install 'pyrtu[tls]'"
        ) from None
    cert = x509.load_der_x509_certificate(der)
    role = None
    try:
        extension = cert.extensions.get_extension_for_oid(x509.ObjectIdentifier(ROLE_OID))
    except x509.ExtensionNotFound:
        pass
    else:
        value = extension.value
        if isinstance(value, x509.UnrecognizedExtension):
            role = _utf8string(value.value)
    return role, cert.subject.rfc4514_string()


def peer_identity(tls: ssl.SSLObject, address: str, port: int | None) -> Identity:
    """Who is at the other end of an established TLS connection."""
    der = tls.getpeercert(binary_form=True)
    if not der:  # CERT_REQUIRED: cannot happen on an established connection
        return Identity(address, port, None, "(no certificate)")
    role, subject = certificate_role(der)
    return Identity(address, port, role, subject)


@dataclass(frozen=True)
class TlsListen:
    """A TLS listener: where, and the `server_context`."""

    host: str
    port: int
    context: ssl.SSLContext


__all__ = [
    "MBAPS_PORT",
    "ROLE_OID",
    "TlsListen",
    "TlsSetupError",
    "certificate_role",
    "client_context",
    "peer_identity",
    "server_context",
]
