"""The options several ``rlbridge`` commands share, defined once so they mean one thing.

:data:`SHORT_OPTIONS` is the only place a short option is given out: ``-H`` is ``--host`` in
every command that has a host (``serve`` and ``demo`` included), ``-t`` is ``--transport``
wherever there is a transport, and no command gives either letter another meaning
(``tests/cli/test_options.py`` walks every command to check). :func:`option` builds a
``typer.Option`` with the long name, its short one if it has one, and the help text.
"""

from __future__ import annotations

import logging
import re
import sys
from typing import TYPE_CHECKING, Annotated, Any

import typer

from rlbridge.cli_errors import fail

if TYPE_CHECKING:
    from pydantic import ValidationError

#: Long option -> its one short form, for every command.
SHORT_OPTIONS: dict[str, str] = {
    "--host": "-H",
    "--port": "-p",
    "--field": "-f",
    "--transport": "-t",
}

LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"


def option(long: str, help: str, **kwargs: Any) -> Any:
    """``typer.Option(long, SHORT_OPTIONS[long], help=...)``; the short one only if it has one."""
    short = SHORT_OPTIONS.get(long)
    return typer.Option(long, *([short] if short else []), help=help, **kwargs)


def check_log_level(value: str | None) -> str | None:
    """A typer callback: one of :data:`LOG_LEVELS` (any case), else one error line, exit 2."""
    if value is None:
        return None
    if value.lower() not in LOG_LEVELS:
        raise fail(f"--log-level must be one of {', '.join(LOG_LEVELS)}, not '{value}'", 2)
    return value.lower()


def check_transport(value: str) -> str:
    """A typer callback: ``udp`` or ``tcp``, checked before the command connects anywhere."""
    if value not in ("udp", "tcp"):
        raise fail(f"--transport must be 'udp' or 'tcp', not '{value}'", 2)
    return value


def configure_logging(level: str) -> None:
    """Log to stderr at ``level``; called again by ``serve`` with its own level (force)."""
    logging.basicConfig(level=level.upper(), stream=sys.stderr, format=LOG_FORMAT, force=True)


LOG_LEVEL_HELP = f"{', '.join(LOG_LEVELS)}."


def config_error(exc: ValidationError) -> str:
    """A config validation error in the command line's words: ``--timeout-ms``, not the
    config field ``timeout_ms`` (the message names the options a user typed)."""
    first = exc.errors()[0]
    fields = [str(p) for p in first["loc"]]
    message = str(first["msg"]).removeprefix("Value error, ")
    message = re.sub(r"\b([a-z]+(?:_[a-z]+)+)\b",
                     lambda m: "--" + m.group(1).replace("_", "-"), message)
    where = ", ".join("--" + f.replace("_", "-") for f in fields)
    return f"{where}: {message}" if where else message


# -- the options of every command that talks to a running server ------------------------
Host = Annotated[str, option("--host", "Bridge server address.")]
Port = Annotated[int, option("--port", "Bridge server port.")]
Field = Annotated[str, option("--field", "Field path ('data', 'linear.x'); '' = whole message.")]
TransportOpt = Annotated[str, option("--transport", "udp or tcp.", callback=check_transport)]
TlsOpt = Annotated[bool, typer.Option("--tls", help="Connect with TLS, trusting the system's "
                                      "CAs (or --ca / --fingerprint).")]
CaOpt = Annotated[str | None, typer.Option("--ca", help="CA file the server's TLS certificate "
                                           "must be signed by (implies --tls).")]
FingerprintOpt = Annotated[str | None, typer.Option(
    "--fingerprint", help="SHA-256 fingerprint of the server's TLS certificate to pin, as "
    "`rlbridge tls init` prints it (implies --tls).")]
PskFileOpt = Annotated[str | None, typer.Option(
    "--psk-file", help="Key file in the server's format (this command's line, else the "
    "default line); without it $RLBRIDGE_PSK.")]
TlsCertOpt = Annotated[str | None, typer.Option(
    "--tls-cert", help="This client's TLS certificate (PEM), for a server started with "
    "--tls-client-ca: mutual TLS, its common name is the client's identity (implies --tls; "
    "needs --tls-key).")]
TlsKeyOpt = Annotated[str | None, typer.Option(
    "--tls-key", help="The key of --tls-cert (PEM).")]


def security(tls: bool, ca: str | None, fingerprint: str | None, tls_cert: str | None,
             tls_key: str | None, psk_file: str | None) -> dict[str, Any]:
    """The client commands' security options as ``Bridge.connect`` keywords.

    ``--tls-cert`` and ``--tls-key`` go together (else a one-line usage error, exit 2) and,
    like ``--ca`` and ``--fingerprint``, turn TLS on.
    """
    if (tls_cert is None) != (tls_key is None):
        raise fail("--tls-cert and --tls-key go together: give both for mutual TLS, or "
                   "neither", 2)
    return {"tls": tls or tls_cert is not None, "ca": ca, "fingerprint": fingerprint,
            "client_cert": None if tls_cert is None else (tls_cert, tls_key),
            "psk_file": psk_file}


def checked_transport(value: str) -> str:
    """``udp`` or ``tcp``, else a one-line usage error (exit 2)."""
    if value not in ("udp", "tcp"):
        raise fail(f"--transport must be 'udp' or 'tcp', not '{value}'", 2)
    return value
