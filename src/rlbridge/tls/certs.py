"""Certificates for a lab: a self-signed server certificate in one command, CAs for tests.

``rlbridge tls init DIR`` calls :func:`init_server`: an ECDSA P-256 key and a certificate valid
for ``localhost``, ``127.0.0.1``, ``::1`` and the names given, written as PEM
(``server.key`` mode 600). Clients then pin its SHA-256 fingerprint, no CA needed. For mutual
TLS, :func:`make_ca` and :func:`issue` make a CA and client certificates whose common name is
the client's identity.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rlbridge.tls.context import fingerprint_of

#: Names every server certificate from ``tls init`` is valid for.
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
DEFAULT_DAYS = 825


@dataclass(frozen=True)
class Issued:
    """A key and the certificate for it."""

    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate

    @property
    def fingerprint(self) -> str:
        return fingerprint_of(self.cert.public_bytes(serialization.Encoding.DER))

    def write(self, cert_path: Path, key_path: Path) -> None:
        """PEM files; the key readable by its owner only."""
        cert_path.write_bytes(self.cert.public_bytes(serialization.Encoding.PEM))
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(self.key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))


def _alt_names(names: Iterable[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for name in dict.fromkeys(names):
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            out.append(x509.DNSName(name))
    return out


def issue(common_name: str, *, names: Iterable[str] = (), ca: Issued | None = None,
          is_ca: bool = False, client: bool = False,
          not_before: datetime.datetime | None = None, days: int = DEFAULT_DAYS) -> Issued:
    """A certificate for ``common_name``, signed by ``ca`` (self-signed without one).

    ``names`` become subject alternative names (what a client checks the host against);
    ``client`` marks it for client authentication, ``is_ca`` lets it sign others.
    """
    key = ec.generate_private_key(ec.SECP256R1())
    start = not_before or datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(
        minutes=5)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    builder = (x509.CertificateBuilder()
               .subject_name(subject)
               .issuer_name(ca.cert.subject if ca else subject)
               .public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(start)
               .not_valid_after(start + datetime.timedelta(days=days))
               .add_extension(x509.BasicConstraints(ca=is_ca, path_length=None), critical=True))
    # Key identifiers and key usage: Python 3.13 verifies with VERIFY_X509_STRICT, which refuses
    # a chain without them ("Missing Authority Key Identifier").
    issuer_key = ca.key.public_key() if ca else key.public_key()
    builder = (builder
               .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                              critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_key),
                              critical=False)
               .add_extension(x509.KeyUsage(
                   digital_signature=True, content_commitment=False, key_encipherment=False,
                   data_encipherment=False, key_agreement=False, key_cert_sign=is_ca,
                   crl_sign=is_ca, encipher_only=False, decipher_only=False), critical=True))
    alt = _alt_names(names)
    if alt:
        builder = builder.add_extension(x509.SubjectAlternativeName(alt), critical=False)
    if not is_ca:
        usage = ExtendedKeyUsageOID.CLIENT_AUTH if client else ExtendedKeyUsageOID.SERVER_AUTH
        builder = builder.add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
    cert = builder.sign(ca.key if ca else key, hashes.SHA256())
    return Issued(key, cert)


def make_ca(common_name: str = "rlbridge lab CA", days: int = DEFAULT_DAYS) -> Issued:
    return issue(common_name, is_ca=True, days=days)


def init_server(directory: Path, names: Iterable[str] = (), *, force: bool = False,
                days: int = DEFAULT_DAYS) -> tuple[Path, Path, str]:
    """Write ``server.key`` and ``server.crt`` in ``directory``; return them and the fingerprint.

    Refuses to overwrite an existing key unless ``force`` (a new key changes the fingerprint
    every client has pinned).
    """
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / "server.crt", directory / "server.key"
    if not force and (cert_path.exists() or key_path.exists()):
        raise FileExistsError(f"{key_path} already exists; pass --force to replace it (every "
                              "client then needs the new fingerprint)")
    extra = list(names)
    issued = issue(extra[0] if extra else "localhost", names=[*LOCAL_NAMES, *extra], days=days)
    issued.write(cert_path, key_path)
    return cert_path, key_path, issued.fingerprint
