"""``rlbridge tls``: certificates for a lab set-up in one command."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

tls_app = typer.Typer(help="TLS certificates: a self-signed server certificate to pin.",
                      no_args_is_help=True)


@tls_app.command("init")
def init(
    directory: Annotated[Path, typer.Argument(metavar="DIR", help="Where to write "
                                              "server.key and server.crt.")],
    name: Annotated[list[str] | None, typer.Option(
        "--name", help="Host name or address clients use, besides localhost and "
        "127.0.0.1 (repeatable).")] = None,
    days: Annotated[int, typer.Option(help="Days the certificate is valid.")] = 825,
    force: Annotated[bool, typer.Option(
        "--force", help="Replace an existing key (clients must pin the new fingerprint).")]
    = False,
) -> None:
    """Write DIR/server.key and DIR/server.crt and print the fingerprint clients pin."""
    from rlbridge.tls.certs import init_server

    try:
        cert, key, fingerprint = init_server(directory, name or (), force=force, days=days)
    except (OSError, ValueError) as exc:
        typer.echo(f"rlbridge: error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"wrote {key} (private: keep it on the server) and {cert}")
    typer.echo(f"sha256 fingerprint: {fingerprint}")
    typer.echo(f"server: rlbridge serve --tls-cert {cert} --tls-key {key} ...")
    typer.echo(f"client: rlbridge topic list --fingerprint {fingerprint} ...")
