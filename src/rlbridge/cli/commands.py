"""The ``rlbridge`` command: each command builds a config and calls the library, nothing more."""

from __future__ import annotations

import functools
import json
from typing import Annotated, Any

import typer

from rlbridge._version import __version__
from rlbridge.cli.errors import fail, one_line_errors
from rlbridge.cli.options import (
    LOCAL_SERVER,
    LOG_LEVEL_HELP,
    Host,
    Port,
    ServerTarget,
    TransportOpt,
    check_log_level,
    checked_transport,
    configure_logging,
    option,
    server_options,
)
from rlbridge.cli.topic import topic_app

#: ``-h`` as well as ``--help``, and help wrapped at 100 columns (or the terminal's width if
#: narrower), in every command: click hands these down to each subcommand's context, and
#: docs/cli.md is the same text at 100 columns (scripts/gen_docs.py).
HELP_OPTIONS: dict[str, Any] = {"help_option_names": ["-h", "--help"], "max_content_width": 100}

app = typer.Typer(
    help="rlbridge: bridge hard-real-time control code to ROS 2 over TCP and UDP.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings=HELP_OPTIONS,
)
app.add_typer(topic_app, name="topic")

LogLevel = Annotated[str | None, typer.Option(
    "--log-level", callback=check_log_level, show_default=False,
    help=f"{LOG_LEVEL_HELP} [default: warning; serve: info]")]


def _version(value: bool) -> None:
    """Version, value path and cipher; when either was not built, what builds it into this
    install (an editable checkout, a checkout, or a wheel), naming only the build packages
    the parts not built need and this machine lacks (rlbridge._version)."""
    if value:
        from rlbridge._compiled import NOT_BUILT, STATE
        from rlbridge._version import compile_hint
        from rlbridge.wire.aead import NOT_BUILT as NO_LIBSODIUM
        from rlbridge.wire.aead import STATE as AEAD

        typer.echo(f"rlbridge {__version__}\nvalue path: {STATE}\n"
                   f"sealing (ChaCha20-Poly1305): {AEAD}")
        unbuilt = [part for part, state, not_built in (("value path", STATE, NOT_BUILT),
                                                       ("cipher", AEAD, NO_LIBSODIUM))
                   if state == not_built]
        if unbuilt:
            typer.echo(f"to compile: {compile_hint(unbuilt)}")
        raise typer.Exit()


@app.callback()
def main_options(
    ctx: typer.Context,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and whether the value path is "
                                               "compiled (mypyc), and exit.")] = False,
    log_level: LogLevel = None,
) -> None:
    """rlbridge: bridge hard-real-time control code to ROS 2 over TCP and UDP."""
    ctx.obj = {"log_level": log_level}
    configure_logging(ctx, log_level or "warning")


@app.command()
@one_line_errors
def serve(
    ctx: typer.Context,
    host: Annotated[str, option("--host", "Address to bind (0.0.0.0 for all interfaces).")]
    = "127.0.0.1",
    port: Annotated[int, option("--port", "TCP and UDP port (0: any free port).")] = 7411,
    tcp: Annotated[bool, typer.Option("--tcp/--no-tcp", help="Accept TCP clients.")] = True,
    udp: Annotated[bool, typer.Option("--udp/--no-udp", help="Accept UDP clients.")] = True,
    nodelay: Annotated[bool, typer.Option(help="Disable Nagle's algorithm (TCP_NODELAY).")]
    = False,
    adapter: Annotated[str, typer.Option(help="Middleware: inproc (default) or ros2.")]
    = "inproc",
    heartbeat_ms: Annotated[int, typer.Option(help="Heartbeat period.")] = 200,
    timeout_ms: Annotated[int, typer.Option(help=(
        "Watchdog: a silent client is dropped after; 2000 on a loaded machine "
        "(docs/reliability.md)."))]
    = 600,
    node_name: Annotated[str, typer.Option(help="ROS 2 node name (adapter ros2).")]
    = "rlbridge",
    namespace: Annotated[str, typer.Option(help="ROS 2 namespace (adapter ros2).")] = "",
    psk_file: Annotated[str | None, typer.Option(
        help="Key file: '<hex>' or '<client-name> <hex>' per line, topic rules optional "
        "(docs/security.md); else $RLBRIDGE_PSK; else no keys.")] = None,
    tls_cert: Annotated[str | None, typer.Option(
        help="TLS certificate (PEM; `rlbridge tls init` makes one): TCP clients need TLS 1.3.")]
    = None,
    tls_key: Annotated[str | None, typer.Option(help="The TLS certificate's key (PEM).")]
    = None,
    tls_client_ca: Annotated[str | None, typer.Option(
        help="Mutual TLS: clients need a certificate this CA signed (its name: their "
        "identity).")] = None,
    insecure: Annotated[bool, typer.Option(
        "--insecure", help="Allow an address other than loopback without TLS or a key "
        "(warned).")] = False,
    allow: Annotated[list[str] | None, typer.Option(
        help="Client network allowed in (repeatable): 192.168.1.0/24, 127.0.0.1. Default: any.")]
    = None,
    max_rate: Annotated[float | None, typer.Option(
        help="Values per second per session; excess dropped and counted.")] = None,
    max_sessions: Annotated[int, typer.Option(help="Concurrent sessions.")] = 256,
    max_channels: Annotated[int, typer.Option(help="Channels per session.")] = 256,
    max_packet: Annotated[int, typer.Option(help="Largest packet body, bytes.")] = 1 << 20,
    udp_receive_buffer: Annotated[int | None, typer.Option(
        help="Bytes of datagrams the UDP socket may queue (default: 32 MiB, or what "
             "net.core.rmem_max allows; docs/load.md).")] = None,
    metrics_port: Annotated[int | None, typer.Option(
        help="Serve /metrics (Prometheus), /healthz and /status (JSON); default: off.")]
    = None,
    metrics_host: Annotated[str, typer.Option(
        help="Address of the metrics endpoint, which asks no key: loopback whatever --host "
             "is (another is warned).")] = "127.0.0.1",
    log_level: LogLevel = None,
) -> None:
    """Run the bridge server until Ctrl-C / SIGTERM (security: docs/security.md).

    It logs a line when it listens and when it stops, and, at most once per 10 s per kind,
    what clients got wrong. Exit status 0 after a clean stop, 1 if it cannot start.
    """
    configure_logging(ctx, log_level or (ctx.obj or {}).get("log_level") or "info")
    from pydantic import ValidationError

    from rlbridge.cli.options import config_error
    from rlbridge.server import Server, ServerConfig

    try:
        config = ServerConfig(host=host, port=port, tcp=tcp, udp=udp, nodelay=nodelay,
                              adapter=adapter, heartbeat_ms=heartbeat_ms,
                              timeout_ms=timeout_ms, node_name=node_name, namespace=namespace,
                              psk_file=psk_file, tls_cert=tls_cert, tls_key=tls_key,
                              tls_client_ca=tls_client_ca, insecure=insecure,
                              allow=tuple(allow or ()), max_rate=max_rate,
                              max_sessions=max_sessions, max_channels=max_channels,
                              max_packet=max_packet, udp_receive_buffer=udp_receive_buffer,
                              metrics_port=metrics_port, metrics_host=metrics_host)
    except ValidationError as exc:
        raise fail(config_error(exc), 2) from None
    Server(config).run()


@app.command()
@one_line_errors
@server_options
def stats(
    server: ServerTarget = LOCAL_SERVER,
    as_json: Annotated[bool, typer.Option("--json", help="Print the whole reply as JSON.")]
    = False,
) -> None:
    """Print the server's counters: totals, then per session and per channel."""
    from rlbridge.server.report import format_stats

    with server.connect("rlbridge-stats") as bridge:
        body = bridge.server_stats()
    typer.echo(json.dumps(body, indent=2, sort_keys=True) if as_json else format_stats(body))


@app.command()
@one_line_errors
def ping(
    host: Host = "127.0.0.1",
    port: Port = 7411,
    transport: TransportOpt = "tcp",
    timeout: Annotated[float, typer.Option(help="Seconds to wait for the answer.")] = 2.0,
) -> None:
    """Exit 0 if a bridge server answers at HOST:PORT, 1 if not: a health probe.

    Any answer counts (a session, a key challenge, a refusal): the server is up. No key is
    needed and no session stays open.
    """
    from rlbridge.cli.ping import ping as probe

    answer = probe(host, port, checked_transport(transport), timeout)
    typer.echo(f"rlbridge server at {host}:{port} ({answer.transport.upper()}) "
               f"{answer.said} in {answer.seconds * 1e3:.1f} ms")


@functools.cache
def build_app() -> typer.Typer:
    """The complete ``rlbridge`` app: :data:`app` with the ``bench``, ``demo`` and ``netem``
    groups added (once; later calls return the same app).

    Those groups are added here rather than at import so ``import rlbridge.cli`` stays light
    (their modules pull in the benchmark, demo and emulator code); the console script and
    ``scripts/gen_docs.py`` both build the app through this function.
    """
    from rlbridge.bench.cli import bench_app
    from rlbridge.cli.ros import action_app, param_app, service_app
    from rlbridge.demo.cli import register_demo

    app.add_typer(service_app, name="service")
    app.add_typer(param_app, name="param")
    app.add_typer(action_app, name="action")
    app.add_typer(bench_app, name="bench")
    register_demo(app)
    from rlbridge.tls.cli import tls_app

    app.add_typer(tls_app, name="tls")
    try:
        from rlbridge.netem.cli import netem_app
    except ImportError:  # the emulator is being built in parallel; the CLI works without it
        pass
    else:
        app.add_typer(netem_app, name="netem")
    _plain_help(app)
    return app


def _plain_help(typer_app: typer.Typer) -> None:
    """Click's plain help and error lines for ``typer_app`` and every group under it.

    With rich installed, typer draws help in boxes, reads ``[default: ...]`` in a help text as
    markup (and drops it) and shows each flag as ``<bool>``; docs/cli.md is click's plain text.
    Plain help everywhere makes the terminal and docs/cli.md one text (scripts/gen_docs.py).
    """
    typer_app.rich_markup_mode = None
    for group in typer_app.registered_groups:
        if group.typer_instance is not None:
            _plain_help(group.typer_instance)


def main() -> None:
    """Console-script entry point."""
    build_app()()

if __name__ == "__main__":
    main()
