"""The ``rlbridge`` command: each command builds a config and calls the library, nothing more."""

from __future__ import annotations

import functools
import itertools
import json
import math
import statistics
import time
from typing import Annotated, Any

import typer

from rlbridge._version import __version__
from rlbridge.cli_errors import fail, one_line_errors
from rlbridge.cli_options import (
    LOG_LEVEL_HELP,
    check_log_level,
    check_transport,
    configure_logging,
    option,
)

app = typer.Typer(
    help="rlbridge: bridge hard-real-time control code to ROS 2 over TCP and UDP.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
topic_app = typer.Typer(help="Publish, echo, measure and list topics through a running server.",
                        no_args_is_help=True)
app.add_typer(topic_app, name="topic")

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
LogLevel = Annotated[str | None, typer.Option(
    "--log-level", callback=check_log_level, show_default=False,
    help=f"{LOG_LEVEL_HELP} [default: warning; serve: info]")]


def _transport(value: str) -> str:
    if value not in ("udp", "tcp"):
        raise fail(f"--transport must be 'udp' or 'tcp', not '{value}'", 2)
    return value


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rlbridge {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    ctx: typer.Context,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
    log_level: LogLevel = None,
) -> None:
    """rlbridge: bridge hard-real-time control code to ROS 2 over TCP and UDP."""
    ctx.obj = {"log_level": log_level}
    configure_logging(log_level or "warning")


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
    timeout_ms: Annotated[int, typer.Option(help="Watchdog: a silent client is dropped after.")]
    = 600,
    node_name: Annotated[str, typer.Option(help="ROS 2 node name (adapter ros2).")]
    = "rlbridge",
    namespace: Annotated[str, typer.Option(help="ROS 2 namespace (adapter ros2).")] = "",
    psk_file: Annotated[str | None, typer.Option(
        help="Key file: hex keys, one line per client ('<hex>' or '<client-name> <hex>'), "
        "optionally with topic rules (docs/security.md); without it $RLBRIDGE_PSK (hex); "
        "without both, no keys. Never a key on the command line.")] = None,
    tls_cert: Annotated[str | None, typer.Option(
        help="TLS certificate (PEM): TCP clients must then use TLS 1.3. `rlbridge tls init` "
        "makes one.")] = None,
    tls_key: Annotated[str | None, typer.Option(help="The TLS certificate's key (PEM).")]
    = None,
    tls_client_ca: Annotated[str | None, typer.Option(
        help="Mutual TLS: clients need a certificate signed by this CA; its common name is "
        "the client's identity.")] = None,
    insecure: Annotated[bool, typer.Option(
        "--insecure", help="Listen on an address other than loopback without TLS or a key "
        "(warned at start); without it such a server refuses to start.")] = False,
    allow: Annotated[list[str] | None, typer.Option(
        help="Client network allowed in (repeatable): 192.168.1.0/24, 127.0.0.1. Default: any.")]
    = None,
    max_rate: Annotated[float | None, typer.Option(
        help="Values per second per session; excess dropped and counted.")] = None,
    max_sessions: Annotated[int, typer.Option(help="Concurrent sessions.")] = 256,
    max_channels: Annotated[int, typer.Option(help="Channels per session.")] = 256,
    max_packet: Annotated[int, typer.Option(help="Largest packet body, bytes.")] = 1 << 20,
    metrics_port: Annotated[int | None, typer.Option(
        help="Serve http://HOST:PORT/metrics (Prometheus), /healthz and /status (JSON); "
             "default: off.")] = None,
    log_level: LogLevel = None,
) -> None:
    """Run the bridge server until Ctrl-C / SIGTERM (security: docs/security.md).

    It logs one line when it listens (address, ports, adapter, authentication) and one when
    it stops, and, at most once per 10 s per kind, what clients got wrong (a wrong key, a
    malformed packet, a refused channel). Exit status 0 after a clean stop, 1 if it cannot
    start.
    """
    configure_logging(log_level or (ctx.obj or {}).get("log_level") or "info")
    from pydantic import ValidationError

    from rlbridge.cli_options import config_error
    from rlbridge.server import Server, ServerConfig

    try:
        config = ServerConfig(host=host, port=port, tcp=tcp, udp=udp, nodelay=nodelay,
                              adapter=adapter, heartbeat_ms=heartbeat_ms,
                              timeout_ms=timeout_ms, node_name=node_name, namespace=namespace,
                              psk_file=psk_file, tls_cert=tls_cert, tls_key=tls_key,
                              tls_client_ca=tls_client_ca, insecure=insecure,
                              allow=tuple(allow or ()), max_rate=max_rate,
                              max_sessions=max_sessions, max_channels=max_channels,
                              max_packet=max_packet,
                              metrics_port=metrics_port)
    except ValidationError as exc:
        raise fail(config_error(exc), 2) from None
    Server(config).run()


def _parse_value(text: str) -> Any:
    """JSON when it parses (numbers, true, objects), the raw text otherwise (strings)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


@topic_app.command("pub")
@one_line_errors
def topic_pub(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE", help="e.g. std_msgs/msg/Float64")],
    value: Annotated[str, typer.Argument(help="JSON value: 1.5, true, \"text\", {\"x\": 1}")],
    field: Field = "data",
    rate: Annotated[float, typer.Option(help="Publish at this rate (Hz); 0 = once.")] = 0.0,
    count: Annotated[int, typer.Option(help="Number of messages (with --rate).")] = 1,
    transport: TransportOpt = "udp",
    host: Host = "127.0.0.1",
    port: Port = 7411,
    tls: TlsOpt = False,
    ca: CaOpt = None,
    fingerprint: FingerprintOpt = None,
    psk_file: PskFileOpt = None,
) -> None:
    """Publish VALUE on TOPIC through the bridge.

    Exits 0 only once the server has counted every value; a value it refuses (not the
    channel's type, over its --max-rate) or a datagram that never arrives makes it exit 1,
    saying how many of how many the server took.
    """
    from rlbridge.cli_delivery import confirm_delivery
    from rlbridge.csp.bridge import Bridge

    parsed = _parse_value(value)
    with Bridge.connect(host, port, name="rlbridge-topic-pub", reconnect=False,
                        tls=tls, ca=ca, fingerprint=fingerprint, psk_file=psk_file) as bridge:
        out = bridge.publish(topic, msg_type, field or None, transport=_transport(transport))  # type: ignore[arg-type]
        n = max(1, count) if rate > 0 else 1
        period = 1.0 / rate if rate > 0 else 0.0
        start = time.monotonic()
        for i in range(n):
            try:
                out.write(parsed)
            except TypeError as exc:  # the SDK checks the value against the field's type
                raise fail(str(exc), 2) from None
            if i + 1 < n:
                time.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))
        bridge.send(wait=True)
        confirm_delivery(bridge, out, n)
    typer.echo(f"published {n} message(s) on {topic}")


@topic_app.command("echo")
@one_line_errors
def topic_echo(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE")],
    field: Field = "data",
    count: Annotated[int, typer.Option(help="Exit after this many values (0 = never).")] = 0,
    transport: TransportOpt = "udp",
    timeout: Annotated[float, typer.Option(help="Exit with an error after this many seconds "
                                                "without a value (0 = wait forever).")] = 0.0,
    host: Host = "127.0.0.1",
    port: Port = 7411,
    tls: TlsOpt = False,
    ca: CaOpt = None,
    fingerprint: FingerprintOpt = None,
    psk_file: PskFileOpt = None,
) -> None:
    """Print each value published on TOPIC, one JSON document per line."""
    from rlbridge.csp.bridge import Bridge

    with Bridge.connect(host, port, name="rlbridge-topic-echo", reconnect=False,
                        tls=tls, ca=ca, fingerprint=fingerprint, psk_file=psk_file) as bridge:
        ch = bridge.subscribe(topic, msg_type, field or None, transport=_transport(transport),  # type: ignore[arg-type]
                              blocking=True, buffer_size=4096)
        seen = 0
        while count == 0 or seen < count:
            try:
                v = _read_while_open(bridge, ch, timeout or None)
            except TimeoutError:
                raise fail(f"no value on {topic} within {timeout} s") from None
            typer.echo(json.dumps(v))
            seen += 1


def _read_while_open(bridge: Any, ch: Any, timeout: float | None) -> Any:
    """A blocking read that gives up once the session ends (the server stopped or closed it).

    Waits in short slices for ``--timeout``; the end of the session (the tools do not
    reconnect) closes the channel, which ends the read with ``ChannelClosed``.
    """
    from rlbridge.csp.connection import ConnectionClosed
    from rlbridge.csp.errors import ChannelClosed

    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
        if left <= 0:
            raise TimeoutError
        try:
            return ch.read(timeout=left)
        except ChannelClosed:
            raise ConnectionClosed(bridge.close_reason) from None
        except TimeoutError:
            if bridge.closed:
                raise ConnectionClosed(bridge.close_reason) from None


@topic_app.command("hz")
@one_line_errors
def topic_hz(
    topic: str,
    msg_type: Annotated[str, typer.Argument(metavar="TYPE")],
    field: Field = "data",
    window: Annotated[int, typer.Option(help="Messages in the rate window.")] = 10000,
    duration: Annotated[float, typer.Option(help="Stop after this many seconds (0 = never).")]
    = 0.0,
    transport: TransportOpt = "udp",
    host: Host = "127.0.0.1",
    port: Port = 7411,
    tls: TlsOpt = False,
    ca: CaOpt = None,
    fingerprint: FingerprintOpt = None,
    psk_file: PskFileOpt = None,
) -> None:
    """Measure the publishing rate of TOPIC, like `rostopic hz` (printed every second).

    With --duration, exits 1 if no value arrived in that time (like echo's --timeout).
    """
    from rlbridge.csp.bridge import Bridge
    from rlbridge.csp.errors import ChannelClosed

    with Bridge.connect(host, port, name="rlbridge-topic-hz", reconnect=False,
                        tls=tls, ca=ca, fingerprint=fingerprint, psk_file=psk_file) as bridge:
        ch = bridge.subscribe(topic, msg_type, field or None, transport=_transport(transport),  # type: ignore[arg-type]
                              blocking=True, buffer_size=65536)
        arrivals: list[float] = []
        end = time.monotonic() + duration if duration > 0 else math.inf
        next_report = time.monotonic() + 1.0
        while time.monotonic() < end:
            try:
                ch.read(timeout=min(1.0, max(0.01, end - time.monotonic())))
            except (TimeoutError, ChannelClosed):
                if bridge.closed:
                    from rlbridge.csp.connection import ConnectionClosed

                    raise ConnectionClosed(bridge.close_reason) from None
            else:
                arrivals.append(time.monotonic())
                arrivals.extend(time.monotonic() for _ in ch.read_many(1 << 16))
                del arrivals[:-window]
            if time.monotonic() >= next_report:
                next_report += 1.0
                typer.echo(format_rate(arrivals))
        typer.echo(format_rate(arrivals))
        if not arrivals:
            raise fail(f"no value on {topic} within {duration:g} s")


def format_rate(arrivals: list[float]) -> str:
    """rostopic-hz-style line from arrival times."""
    if len(arrivals) < 2:
        return "no new messages"
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    mean = statistics.fmean(gaps)
    rate = 1.0 / mean if mean > 0 else math.inf
    std = statistics.pstdev(gaps)
    return (f"average rate: {rate:.3f}\n\tmin: {min(gaps):.6f}s max: {max(gaps):.6f}s "
            f"std dev: {std:.6f}s window: {len(arrivals)}")


@topic_app.command("list")
@one_line_errors
def topic_list(
    host: Host = "127.0.0.1",
    port: Port = 7411,
    tls: TlsOpt = False,
    ca: CaOpt = None,
    fingerprint: FingerprintOpt = None,
    psk_file: PskFileOpt = None,
    show_types: Annotated[bool, option("--show-types", "Print types too.")]
    = False,
) -> None:
    """List the topics the server's middleware knows."""
    from rlbridge.csp.bridge import Bridge

    with Bridge.connect(host, port, name="rlbridge-topic-list", reconnect=False,
                        tls=tls, ca=ca, fingerprint=fingerprint, psk_file=psk_file) as bridge:
        for name, msg_type in bridge.server_stats()["topics"]:
            typer.echo(f"{name} [{msg_type}]" if show_types else name)


@app.command()
@one_line_errors
def stats(
    host: Host = "127.0.0.1",
    port: Port = 7411,
    tls: TlsOpt = False,
    ca: CaOpt = None,
    fingerprint: FingerprintOpt = None,
    psk_file: PskFileOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the whole reply as JSON.")]
    = False,
) -> None:
    """Print the server's counters: totals, then per session and per channel."""
    from rlbridge.csp.bridge import Bridge
    from rlbridge.server.report import format_stats

    with Bridge.connect(host, port, name="rlbridge-stats", reconnect=False,
                        tls=tls, ca=ca, fingerprint=fingerprint, psk_file=psk_file) as bridge:
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
    from rlbridge.ping import ping as probe

    answer = probe(host, port, _transport(transport), timeout)
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
    from rlbridge.demo.cli import register_demo

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
    return app


def main() -> None:
    """Console-script entry point."""
    build_app()()

if __name__ == "__main__":
    main()
