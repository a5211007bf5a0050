"""Certificates for the TLS tests, made with the `cryptography` package: a CA, the
server's (localhost, 127.0.0.1), clients with a role, without one, expired, not yet
valid, self-signed, and one signed by another CA.  The role extension
1.3.6.1.4.1.50316.802.1 holds a DER UTF8String (tag 0x0C, X.690 8.23), encoded here
from X.690, not by pyrtu."""

from __future__ import annotations

import datetime
import ipaddress
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROLE_OID = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
NOW = datetime.datetime.now(datetime.timezone.utc)
DAY = datetime.timedelta(days=1)


def utf8string(text: str) -> bytes:
    data = text.encode("utf-8")
    if len(data) < 0x80:
        return bytes((0x0C, len(data))) + data
    size = (len(data).bit_length() + 7) // 8
    return bytes((0x0C, 0x80 | size)) + len(data).to_bytes(size, "big") + data


@dataclass
class Pair:
    cert: Path
    key: Path


def _name(common: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common)])


def _write(
    folder: Path, stem: str, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey
) -> Pair:
    c, k = folder / f"{stem}.crt", folder / f"{stem}.key"
    c.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    k.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return Pair(c, k)


class Authority:
    """A CA that signs certificates into ``folder``."""

    def __init__(self, folder: Path, name: str = "test CA") -> None:
        self.folder = folder
        self.key = ec.generate_private_key(ec.SECP256R1())
        self.name = _name(name)
        self.cert = (
            x509.CertificateBuilder()
            .subject_name(self.name)
            .issuer_name(self.name)
            .public_key(self.key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(NOW - DAY)
            .not_valid_after(NOW + 30 * DAY)
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(False, False, False, False, False, True, True, False, False),
                critical=True,
            )
            .sign(self.key, hashes.SHA256())
        )
        self.path = folder / f"{name.replace(' ', '_')}.crt"
        self.path.write_bytes(self.cert.public_bytes(serialization.Encoding.PEM))

    def issue(
        self,
        stem: str,
        common: str,
        *,
        role: bytes | str | None = None,
        server: bool = False,
        before: datetime.datetime | None = None,
        after: datetime.datetime | None = None,
        self_signed: bool = False,
        names: tuple[str, ...] = ("localhost",),
    ) -> Pair:
        """A certificate; ``role``: text (encoded as a UTF8String) or raw DER bytes."""
        key = ec.generate_private_key(ec.SECP256R1())
        subject = _name(common)
        builder = (
            x509.CertificateBuilder()
            .subject_name(subject)
            .issuer_name(subject if self_signed else self.name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(before or NOW - DAY)
            .not_valid_after(after or NOW + 30 * DAY)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        )
        usage = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
        builder = builder.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        if server:
            builder = builder.add_extension(
                x509.SubjectAlternativeName(
                    [x509.DNSName(name) for name in names]
                    + [x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
                    * (names == ("localhost",))
                ),
                critical=False,
            )
        if role is not None:
            value = utf8string(role) if isinstance(role, str) else role
            builder = builder.add_extension(
                x509.UnrecognizedExtension(ROLE_OID, value), critical=False
            )
        cert = builder.sign(key if self_signed else self.key, hashes.SHA256())
        return _write(self.folder, stem, cert, key)


@dataclass
class Pki:
    ca: Authority
    server: Pair
    operator: Pair
    viewer: Pair
    no_role: Pair
    unknown_role: Pair
    expired: Pair
    not_yet_valid: Pair
    self_signed: Pair
    other_ca: Pair
    other: Authority


def make_pki(folder: Path) -> Pki:
    ca = Authority(folder)
    other = Authority(folder, "other CA")
    return Pki(
        ca=ca,
        server=ca.issue("server", "localhost", server=True),
        operator=ca.issue("operator", "panel1", role="operator"),
        viewer=ca.issue("viewer", "screen", role="viewer"),
        no_role=ca.issue("norole", "nobody"),
        unknown_role=ca.issue("admin", "intruder", role="admin"),
        expired=ca.issue("expired", "old", role="operator", before=NOW - 10 * DAY, after=NOW - DAY),
        not_yet_valid=ca.issue(
            "future", "early", role="operator", before=NOW + DAY, after=NOW + 10 * DAY
        ),
        self_signed=ca.issue("selfsigned", "self", role="operator", self_signed=True),
        other_ca=other.issue("otherca", "stranger", role="operator"),
        other=other,
    )
