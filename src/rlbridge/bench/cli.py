"""``rlbridge bench ...``: thin typer commands over the benchmark modules.

A report goes to stdout and nowhere else unless ``--out FILE`` asks: run from a checkout, a
default file would rewrite committed pages; run anywhere else, it would create one in the
user's directory.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer

from rlbridge.cli.options import BundlesOpt, IdleOpt, idle_specs

bench_app = typer.Typer(help="Measure rlbridge next to a baseline from the same run. The report "
                        "goes to stdout; --out FILE also writes it into FILE.",
                        no_args_is_help=True)

Out = Annotated[Path | None, typer.Option(
    "--out", help="Also write the report into this markdown file (its own section replaced or "
    "appended, the rest kept). Default: stdout only, no file written.")]


@bench_app.command("ros2")
def ros2(
    ctx: typer.Context,
    rate_hz: Annotated[float, typer.Option("--rate-hz", help="Latency stream rate.")] = 1000.0,
    count: Annotated[int, typer.Option(help="Latency samples per run.")] = 3000,
    seconds: Annotated[float, typer.Option(help="Flood length per throughput run.")] = 2.0,
    repeats: Annotated[int, typer.Option(help="Runs per row; medians over them.")] = 3,
    modes: Annotated[str, typer.Option(help="latency, throughput or both.")]
    = "latency,throughput",
    only: Annotated[str, typer.Option(help="Rows: rclpy, in-tcp, in-udp, out-tcp, out-udp.")]
    = "",
    out: Out = None,
) -> None:
    """Values/s and latency through the ROS 2 adapter, next to rclpy node -> node (same run)."""
    from rlbridge.bench import ros2 as r2
    from rlbridge.bench.common import LoopbackLink, progress

    _run("ros2", lambda: r2.bench(LoopbackLink(), r2.Settings(
        rate_hz=rate_hz, count=count, seconds=seconds, repeats=repeats,
        modes=r2.parse_modes(modes), only=_keys(only)), _command(ctx), progress), out)

# -- throughput and latency (rlbridge.bench.throughput, .latency) ----------------------------
Repeats = Annotated[int, typer.Option(help="Runs per row; figures are medians over them.")]
_ONLY = "Comma-separated row keys (default: every row): "


def _command(ctx: typer.Context) -> list[str]:
    """The command line with every option spelled out, so the report can be re-run exactly."""
    args = ["rlbridge", "bench", ctx.info_name or ""]
    for name, value in ctx.params.items():
        flag = f"--{name.replace('_', '-')}"
        if isinstance(value, bool):  # an on/off flag: --x or --no-x
            args.append(flag if value else f"--no-{flag[2:]}")
        elif value is not None and value != "":
            args += [flag, str(value)]
    return args


def _run(name: str, measure: Callable[[], str], out: Path | None) -> None:
    """Run, print the markdown (and write its section of ``out`` if given); a failed run is
    one line."""
    from rlbridge.bench.common import BenchError, write_section

    try:
        text = measure()
    except BenchError as exc:
        typer.echo(f"rlbridge bench {name}: error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(text)
    if out is not None:
        write_section(out, name, text)


def _keys(only: str) -> tuple[str, ...]:
    return tuple(k.strip() for k in only.split(",") if k.strip())


@bench_app.command("throughput")
def throughput(
    ctx: typer.Context,
    count: Annotated[int, typer.Option(help="Values per run (at most).")] = 2_000_000,
    seconds: Annotated[float, typer.Option(help="Longest send phase of a run.")] = 3.0,
    repeats: Repeats = 3,
    batch: Annotated[int, typer.Option(help="write_many size of the batched rows.")] = 4096,
    rate: Annotated[float, typer.Option(help="Offered values/s of rlbridge rows (0: flood).")]
    = 0.0,
    only: Annotated[str, typer.Option(help=_ONLY + "udp, zmq, zenoh, rlb-udp-1, "
                                      "rlb-udp-1-single, rlb-tcp-1, "
                                      "rlb-udp-batch, rlb-tcp-batch, rlb-tcp-batch-noflow, "
                                      "rlb-tcp-slow-flow, "
                                      "rlb-tcp-slow-noflow, rlb-tcp-send, rlb-tcp-send-spin, "
                                      "rlb-tcp-send-wait, rlb-tcp-send-wait-spin.")] = "",
    out: Out = None,
) -> None:
    """Values/s publisher -> server -> subscriber (TCP, UDP), next to UDP/ZeroMQ/Zenoh."""
    from rlbridge.bench import throughput as tp
    from rlbridge.bench.common import LoopbackLink, progress
    from rlbridge.bench.throughput_report import report

    settings = tp.Settings(count=count, seconds=seconds, repeats=repeats, batch=batch,
                           rate=rate, only=_keys(only))
    _run("throughput", lambda: report(tp.run(LoopbackLink(), settings, progress), settings,
                                      _command(ctx)), out)


@bench_app.command("feedback")
def feedback(
    ctx: typer.Context,
    seconds: Annotated[float, typer.Option(help="Flood length per run.")] = 2.0,
    repeats: Repeats = 5,
    only: Annotated[str, typer.Option(help=_ONLY + "flood, flood-adapt.")] = "",
    out: Out = None,
) -> None:
    """How soon a UDP flood's first-hop loss shows in the publisher's health() (target 1 s)."""
    from rlbridge.bench import feedback as fb
    from rlbridge.bench.common import LoopbackLink, progress

    _run("feedback", lambda: fb.report(
        fb.run(LoopbackLink(), repeats, seconds, _keys(only), progress), repeats, seconds,
        _command(ctx)), out)


@bench_app.command("latency")
def latency(
    ctx: typer.Context,
    seconds: Annotated[float, typer.Option(help="Stream length per run.")] = 5.0,
    count: Annotated[int | None, typer.Option(help="Samples per run (overrides --seconds).")]
    = None,
    repeats: Repeats = 3,
    rates: Annotated[str, typer.Option(help="Comma-separated stream rates in Hz.")]
    = "1000,100",
    only: Annotated[str, typer.Option(help=_ONLY + "udp, zmq, rlb-udp, rlb-udp-inline, "
                                      "rlb-tcp-nodelay, rlb-tcp-nagle.")] = "",
    out: Out = None,
    transport: Annotated[str | None, typer.Option(
        help="tcp (Nagle), tcpn (nodelay both ends), udp or all: measure across the emulated "
             "link (root) instead of loopback.")] = None,
    delay: Annotated[float, typer.Option(help="Emulated one-way delay, ms (data direction).")]
    = 0.0,
    loss: Annotated[float, typer.Option(help="Emulated loss, percent (data direction).")] = 0.0,
    rate: Annotated[float, typer.Option(help="Stream rate on the emulated link, Hz.")] = 100.0,
    direction: Annotated[str, typer.Option(
        help="down: middleware -> client (thesis A to D); up: client -> middleware.")]
    = "down",
    csv: Annotated[Path | None, typer.Option(
        "--csv", help="Per-sample CSV: seq,sent_ns,recv_ns,latency_ms (empty when lost).")]
    = None,
    idle: IdleOpt = "",
    stages: Annotated[bool, typer.Option(
        "--stages/--no-stages",
        help="Probe rlbridge UDP at the first rate stage by stage (send thread, server, receive "
             "thread, reader), per --idle strategy (default park), next to a raw UDP pair.")]
    = False,
) -> None:
    """One-way latency p50/p99/max of 1 kHz and 100 Hz streams, next to raw UDP and ZeroMQ.

    With --transport, --delay, --loss or --csv: the thesis's set-up instead, bridge server and
    middleware publisher in one network namespace, the SDK client in another, the emulated
    link (docs/netem.md) between them; a table on stdout, per-sample rows to --csv.
    """
    from rlbridge.bench import latency as lat
    from rlbridge.bench.common import LoopbackLink, progress

    if transport is not None or delay or loss or csv is not None:
        _latency_link(transport or "all", delay, loss, rate, count or 1000, direction, csv)
        return
    try:
        strategies = idle_specs(idle)
    except ValueError as exc:
        typer.echo(f"rlbridge bench latency: error: {exc}", err=True)
        raise typer.Exit(2) from None
    if stages:
        _latency_stages(ctx, strategies or ("park",), seconds, repeats,
                        float(_keys(rates)[0]), out)
        return
    settings = lat.Settings(seconds=seconds, count=count, repeats=repeats,
                            rates=tuple(float(r) for r in _keys(rates)), only=_keys(only),
                            idle=strategies)
    # The idle study has its own section: the plain run's figures stay where they are.
    _run("latency-idle" if strategies else "latency",
         lambda: lat.report(lat.run(LoopbackLink(), settings, progress), settings,
                            _command(ctx)), out)


@bench_app.command("cpu")
def cpu(
    ctx: typer.Context,
    channels: Annotated[int, typer.Option(help="UDP channels, published and read back.")] = 10,
    rate: Annotated[float, typer.Option(help="Values/s per channel.")] = 1000.0,
    seconds: Annotated[float, typer.Option(help="Length of each run.")] = 10.0,
    repeats: Repeats = 3,
    out: Out = None,
) -> None:
    """CPU per value of one SDK client with many UDP channels: SDK and server; bundled or
    not, send() per tick or the SDK's send loop."""
    from rlbridge.bench import cpu as cp
    from rlbridge.bench.common import progress

    s = cp.Settings(channels=channels, rate_hz=rate, seconds=seconds, repeats=repeats)
    _run("cpu", lambda: cp.report(cp.run(s, progress), s, _command(ctx)), out)


# -- load (rlbridge.bench.load) ------------------------------------------------
Clients = Annotated[int, typer.Option(help="Concurrent client sessions.")]
Channels = Annotated[int, typer.Option(help="Channels per session (published and subscribed).")]
RateHz = Annotated[float, typer.Option("--rate", help="Values/s per channel.")]
Procs = Annotated[int, typer.Option(help="OS processes the client sessions are spread over.")]
Via = Annotated[str, typer.Option(help="Transport of SDK client channels: udp or tcp.")]
Client = Annotated[str, typer.Option(help="raw: protocol-level UDP sessions, one thread per "
                                     "process; sdk: a Bridge per session.")]
ServerRcvbuf = Annotated[int, typer.Option(
    help="Bytes the server asks for its UDP receive buffer (serve --udp-receive-buffer).")]


def _check_client(client: str, transport: str) -> None:
    if client not in ("raw", "sdk"):
        raise typer.BadParameter(f"--client must be 'raw' or 'sdk', not '{client}'")
    if transport not in ("udp", "tcp"):
        raise typer.BadParameter(f"--transport must be 'udp' or 'tcp', not '{transport}'")


@bench_app.command("load")
def load(
    ctx: typer.Context, clients: Clients = 100, channels: Channels = 10, rate: RateHz = 100.0,
    processes: Procs = 4, transport: Via = "udp", client: Client = "raw",
    bundles: BundlesOpt = True,
    phase_s: Annotated[float, typer.Option(help="Seconds per phase (base, reader, slow, after).")]
    = 20.0,
    slow_topics: Annotated[int, typer.Option(help="Topics the slow consumer subscribes.")]
    = 100,
    udp_receive_buffer: ServerRcvbuf = 32 << 20,
    out: Out = None,
) -> None:
    """100 clients x 10 channels x 100 Hz on one server, and a consumer that stops reading."""
    from rlbridge.bench import load as ld
    from rlbridge.bench.common import progress

    _check_client(client, transport)
    s = ld.Settings(clients=clients, channels=channels, rate_hz=rate, processes=processes,
                    transport=transport, client=client, phase_s=phase_s, slow_topics=slow_topics,
                    warmup_s=min(10.0, phase_s), bundles=bundles,
                    udp_receive_buffer=udp_receive_buffer)
    _run("load", lambda: ld.report(ld.run(s, ld.load_plan(s), progress), _command(ctx)), out)


def _latency_stages(ctx: typer.Context, strategies: tuple[str, ...], seconds: float,
                    repeats: int, rate_hz: float, out: Path | None) -> None:
    from rlbridge.bench import latency_stages as st
    from rlbridge.bench.common import LoopbackLink, progress

    def measure() -> str:
        results, raw = st.run(LoopbackLink(), strategies, seconds=seconds, repeats=repeats,
                              rate_hz=rate_hz, progress=progress)
        return st.report(results, raw, seconds=seconds, repeats=repeats, rate_hz=rate_hz,
                         command=_command(ctx))

    _run("latency-stages", measure, out)


def _latency_link(transport: str, delay: float, loss: float, rate: float, count: int,
                  direction: str, csv: Path | None) -> None:
    from rlbridge.bench import latency_link
    from rlbridge.bench.common import BenchError

    keys = latency_link.TRANSPORT_KEYS if transport == "all" else (transport,)
    try:
        typer.echo(latency_link.run(transports=keys, delay_ms=delay, loss_pct=loss,
                                    rate_hz=rate, count=count, direction=direction, csv=csv,
                                    echo=lambda m: typer.echo(m, err=True)))
    except (BenchError, ValueError) as exc:
        typer.echo(f"rlbridge bench latency: error: {exc}", err=True)
        raise typer.Exit(1) from None
