"""TLS contexts for the server and the client, and certificate pinning.

Both ends insist on TLS 1.3. The server loads its certificate and key, and with a client CA
asks every client for a certificate signed by it (mutual TLS; the certificate's common name is
then the client's identity for authorization). The client trusts the system's CAs
(``tls=True``), a CA file (``ca=``), a context of its own, or exactly one certificate given by
its SHA-256 fingerprint (``fingerprint=``, for the self-signed certificate of
``rlbridge tls init``): pinning replaces the CA check, but the certificate's validity dates
are still checked.
"""

from __future__ import annotations

import datetime
import hashlib
import ssl
from dataclasses import dataclass
from pathlib import Path

from rlbridge.errors import TlsError


def fingerprint_of(der: bytes) -> str:
    """The SHA-256 fingerprint of a DER certificate, as lower-case hex (what ``--fingerprint``
    takes; colons, spaces, case and a ``sha256:`` prefix are ignored there)."""
    return hashlib.sha256(der).hexdigest()


def normalize_fingerprint(text: str) -> str:
    """``text`` as 64 lower-case hex digits; ``ValueError`` naming the problem otherwise."""
    clean = text.strip().lower()
    clean = clean.removeprefix("sha256:").removeprefix("sha256 ")
    clean = clean.replace(":", "").replace(" ", "")
    if len(clean) != 64 or any(c not in "0123456789abcdef" for c in clean):
        raise ValueError(f"fingerprint {text!r} is not a SHA-256 fingerprint (64 hex digits, "
                         "as `rlbridge tls init` prints it)")
    return clean


def server_context(cert: Path, key: Path, client_ca: Path | None = None) -> ssl.SSLContext:
    """The server's TLS 1.3 context; ``TlsError`` names the file that cannot be used."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    try:
        ctx.load_cert_chain(cert, key)
    except FileNotFoundError as exc:
        raise TlsError(f"cannot read {exc.filename}: no such file") from None
    except (ssl.SSLError, OSError) as exc:
        raise TlsError(f"cannot use the TLS certificate {cert} with the key {key}: "
                       f"{_why(exc)}") from None
    if client_ca is not None:
        try:
            ctx.load_verify_locations(cafile=client_ca)
        except (ssl.SSLError, OSError) as exc:
            raise TlsError(f"cannot use the client CA file {client_ca}: {_why(exc)}") from None
        ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


@dataclass(frozen=True)
class ClientTls:
    """How a client checks the server: a context, and a pinned fingerprint or not."""

    context: ssl.SSLContext
    fingerprint: str | None = None

    def check(self, der: bytes | None, now: datetime.datetime | None = None) -> None:
        """After the handshake: the pinned certificate, and its dates (``TlsError`` if not)."""
        if self.fingerprint is None:
            return
        if der is None:
            raise TlsError("the server sent no certificate")
        got = fingerprint_of(der)
        if got != self.fingerprint:
            raise TlsError(f"the server's certificate has fingerprint {got}, not the pinned "
                           f"{self.fingerprint}: not the server you meant, or its certificate "
                           "was replaced")
        from cryptography import x509

        cert = x509.load_der_x509_certificate(der)
        now = now or datetime.datetime.now(datetime.timezone.utc)
        if now < cert.not_valid_before_utc:
            raise TlsError(f"the server's certificate is not valid yet (from "
                           f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC)")
        if now > cert.not_valid_after_utc:
            raise TlsError(f"the server's certificate expired on "
                           f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC")


def client_tls(tls: bool | ssl.SSLContext | None = None, *, ca: str | Path | None = None,
               fingerprint: str | None = None,
               client_cert: tuple[str | Path, str | Path] | None = None) -> ClientTls | None:
    """The client's TLS settings, or None for plaintext.

    TLS is on when ``tls`` is true or a context, or when ``ca`` or ``fingerprint`` is given.
    ``client_cert`` is this client's ``(certificate, key)`` files for a server that requires
    one.
    """
    if not (tls or ca or fingerprint):
        if client_cert:
            raise ValueError("a client certificate needs TLS: add tls=True, ca= or fingerprint=")
        return None
    pinned = normalize_fingerprint(fingerprint) if fingerprint else None
    if isinstance(tls, ssl.SSLContext):
        if ca or pinned:
            raise ValueError("give either an SSLContext or ca=/fingerprint=, not both")
        return ClientTls(tls)
    if pinned is not None:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE  # the pin replaces the CA check (ClientTls.check)
    else:
        try:
            ctx = ssl.create_default_context(cafile=str(ca) if ca else None)
        except (ssl.SSLError, OSError) as exc:
            raise TlsError(f"cannot use the CA file {ca}: {_why(exc)}") from None
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    if client_cert:
        cert, key = client_cert
        try:
            ctx.load_cert_chain(str(cert), str(key))
        except (ssl.SSLError, OSError) as exc:
            raise TlsError(f"cannot use the client certificate {cert}: {_why(exc)}") from None
    return ClientTls(ctx, pinned)


def _why(exc: OSError) -> str:
    if isinstance(exc, ssl.SSLError):
        return exc.reason or str(exc)
    return exc.strerror or str(exc)
