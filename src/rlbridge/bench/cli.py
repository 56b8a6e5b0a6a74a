"""``rlbridge bench ...``: thin typer commands over the benchmark modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

bench_app = typer.Typer(help="Measure rlbridge next to a baseline from the same run.",
                        no_args_is_help=True)

Out = Annotated[Path, typer.Option("--out", help="Markdown file the figures are written to.")]


@bench_app.command("jitter")
def jitter(
    suite: Annotated[str, typer.Option(help="patterns (thesis 5.3) or gil (docs/gil.md).")]
    = "patterns",
    cycles: Annotated[int, typer.Option(help="Deadlines per run.")] = 5000,
    period_us: Annotated[int, typer.Option("--period-us", help="Loop period.")] = 1000,
    repeats: Annotated[int, typer.Option(help="Rounds; figures are medians over them.")] = 3,
    stress: Annotated[bool, typer.Option(help="Run `stress --cpu 2 --io 2 --hdd 1` meanwhile.")]
    = False,
    publish_hz: Annotated[float, typer.Option(help="Rate of the set-point publisher.")] = 100.0,
    only: Annotated[str, typer.Option(help="Comma-separated scenarios (plus the reference).")]
    = "",
    priority: Annotated[bool, typer.Option("--rt/--no-rt",
                                           help="PriParallel priorities for the loop.")] = True,
    out: Out = Path("docs/jitter.md"),
    plot: Annotated[Path, typer.Option(help="PNG of the jitter per cycle.")]
    = Path("docs/jitter.png"),
) -> None:
    """HRT loop jitter per coupling pattern, next to a reference loop from the same run."""
    import sys

    from rlbridge.bench.jitter import JitterConfig, command_line, run

    if suite not in ("patterns", "gil"):
        raise typer.BadParameter("--suite must be 'patterns' or 'gil'")
    run(JitterConfig(suite=suite, cycles=cycles, period=period_us / 1e6,  # type: ignore[arg-type]
                     repeats=repeats, stress=stress, publish_hz=publish_hz,
                     only=tuple(s for s in only.split(",") if s), priority=priority, out=out,
                     plot=plot, command=command_line(sys.argv[1:])), typer.echo)


@bench_app.command("channels")
def channels(
    n: Annotated[int, typer.Option(help="Operations per measurement.")] = 200_000,
    repeats: Annotated[int, typer.Option(help="Repeats; figures are medians.")] = 5,
    out: Out = Path("docs/bench-channels.md"),
) -> None:
    """ns per channel write/read/hand-off, next to queue.Queue and deque from the same run."""
    from rlbridge.bench.channels import format_markdown, run_channel_bench

    text = format_markdown(run_channel_bench(n, repeats))
    out.write_text(text)
    typer.echo(text)
