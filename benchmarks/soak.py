"""``python -m benchmarks.soak``: the load benchmark held for minutes, one report row per interval.

A leak or a queue that creeps shows as a server RSS that keeps rising from row to row, or a
latency that drifts; a healthy server settles after the first interval and stays. The clients,
server and measurements are those of ``rlbridge bench load`` (without the slow consumer).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated

import typer

from rlbridge.bench.common import (
    BenchError,
    fmt,
    markdown_table,
    progress,
    report_header,
    write_section,
)
from rlbridge.bench.load import (
    Plan,
    Run,
    Settings,
    describe,
    loss_by_stage,
    phase_row,
    run,
    totals_line,
)
from rlbridge.server.config import UDP_RECEIVE_BUFFER


def soak_plan(minutes: float, interval_s: float) -> Plan:
    n = max(1, round(minutes * 60 / interval_s))
    return [(f"{(i + 1) * interval_s / 60:.2f}", interval_s, None) for i in range(n)]


def measure(settings: Settings, minutes: float, interval_s: float,
            progress: Callable[[str], None]) -> Run:
    return run(settings, soak_plan(minutes, interval_s), progress)


def report(r: Run, command: Sequence[str]) -> str:
    s = r.settings
    headers = ["t (min)", "written values/s", "delivered values/s",
               "latency p50 µs (median session)", "p99 µs (median session)",
               "p99 µs (worst session)",
               "server receive queue MiB (max)", "hop 1: datagrams dropped by the kernel",
               "server dropped",
               "server CPU %", "server CPU µs per value (in + out)", "server waited for a CPU %",
               "clients CPU % (all processes)", "server RSS MiB (end of interval)"]
    rows, rss = [], []
    for ph in r.phases:
        x = phase_row(ph)
        rss.append(x["rss1"])
        rows.append([ph.name, fmt(x["offered"]), fmt(x["delivered"]), fmt(x["p50"]), fmt(x["p99"]),
                     fmt(x["p99_worst"]), f"{x['queued_max']:.1f}", fmt(x["hop1_drops"]),
                     fmt(x["dropped"]),
                     fmt(x["cpu_pct"]),
                     fmt(x["cpu_us_per_value"], 1), fmt(x["wait_pct"]),
                     fmt(x["clients_cpu_pct"]), f"{x['rss1']:.1f}"])
    growth = (f"Server RSS from the end of the first interval to the end of the last: "
              f"{rss[0]:.1f} -> {rss[-1]:.1f} MiB ({rss[-1] - rss[0]:+.1f} MiB)." if rss else "")
    return "\n".join([
        report_header("Soak: load held over time", command), "",
        f"{s.clients} sessions x {s.channels} channels at {s.rate_hz:g} Hz (offered "
        f"{s.offered:,.0f} values/s) {describe(s)}; a row every {r.phases[0].seconds:.0f} s after "
        f"{s.warmup_s:g} s of warm-up." if r.phases else "", "",
        markdown_table(headers, rows), "", totals_line(r), growth, "", loss_by_stage(r), "",
        f"Load average before: {', '.join(f'{v:.2f}' for v in r.load_before)}; after: "
        f"{', '.join(f'{v:.2f}' for v in r.load_after)}.",
    ]) + "\n"


app = typer.Typer(add_completion=False)


@app.command()
def main(
    ctx: typer.Context,
    minutes: Annotated[float, typer.Option(help="Length of the soak.")] = 5,
    interval_s: Annotated[float, typer.Option(help="Seconds per report row.")] = 30.0,
    clients: Annotated[int, typer.Option(help="Concurrent client sessions.")] = 50,
    channels: Annotated[int, typer.Option(
        help="Channels per session (published and subscribed).")] = 10,
    rate: Annotated[float, typer.Option("--rate", help="Values/s per channel.")] = 100.0,
    processes: Annotated[int, typer.Option(
        help="OS processes the client sessions are spread over.")] = 2,
    transport: Annotated[str, typer.Option(
        help="Transport of SDK client channels: udp or tcp.")] = "udp",
    client: Annotated[str, typer.Option(help="raw: protocol-level UDP sessions, one thread per "
                                        "process; sdk: a Bridge per session.")] = "raw",
    bundles: Annotated[bool, typer.Option(
        help="Every channel of a session's tick in one datagram, both ways; --no-bundles: one "
             "datagram per value.")] = True,
    client_nice: Annotated[int, typer.Option(
        min=0, max=19, help="Niceness added to the client processes: the load generator yields "
        "the CPU to the server it measures (0: same priority).")] = 0,
    udp_receive_buffer: Annotated[int, typer.Option(
        help="Bytes the server asks for its UDP receive buffer (serve --udp-receive-buffer).")]
    = UDP_RECEIVE_BUFFER,
    out: Annotated[Path, typer.Option("--out", help="Markdown file the figures are written to.")]
    = Path("benchmarks/results/soak.md"),
) -> None:
    """Load held for MINUTES: server RSS and latency per interval (a leak shows as a trend)."""
    if client not in ("raw", "sdk"):
        raise typer.BadParameter(f"--client must be 'raw' or 'sdk', not '{client}'")
    if transport not in ("udp", "tcp"):
        raise typer.BadParameter(f"--transport must be 'udp' or 'tcp', not '{transport}'")
    s = Settings(clients=clients, channels=channels, rate_hz=rate, processes=processes,
                 transport=transport, client=client, warmup_s=min(10.0, interval_s),
                 bundles=bundles, udp_receive_buffer=udp_receive_buffer,
                 client_nice=client_nice)
    command = ["python", "-m", "benchmarks.soak"]
    for name, value in ctx.params.items():
        flag = f"--{name.replace('_', '-')}"
        command += ([flag if value else f"--no-{flag[2:]}"] if isinstance(value, bool)
                    else [flag, str(value)])
    try:
        text = report(measure(s, minutes, interval_s, progress), command)
    except BenchError as exc:
        typer.echo(f"benchmarks.soak: error: {exc}", err=True)
        raise typer.Exit(1) from None
    typer.echo(text)
    write_section(out, "soak", text)


if __name__ == "__main__":
    app()
