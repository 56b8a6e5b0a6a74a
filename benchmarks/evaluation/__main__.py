"""``python -m benchmarks.evaluation``: every network scenario of the thesis in one run."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from benchmarks import RESULTS
from benchmarks.evaluation import report as evaluation_report
from benchmarks.evaluation import sweep
from rlbridge.bench.common import BenchError, progress

app = typer.Typer(add_completion=False)


@app.command()
def evaluation(
    out: Annotated[Path, typer.Option("--out", help="Markdown file the figures are written to.")]
    = Path("benchmarks/results/evaluation.md"),
    quick: Annotated[bool, typer.Option(
        help="Fewer scenarios and samples (about 3 minutes instead of ~12).")] = False,
    count: Annotated[int | None, typer.Option(
        help="Samples per latency row (default 1000, --quick 200).")] = None,
    rt_priority: Annotated[int, typer.Option(
        help="SCHED_FIFO priority of the measured processes in latency rows (0: off).")] = 5,
    results: Annotated[Path, typer.Option(help="Directory of the raw summaries (JSON, CSV).")]
    = RESULTS / "evaluation",
) -> None:
    """Every network scenario of the thesis (appendix A, fig. 4.2-4.4, tables 3.1/3.2).

    Needs root (the network emulator). Writes --out, its PNGs under <out dir>/figures/evaluation/
    and the raw summaries under --results.
    """
    settings = sweep.EvalSettings(count=count or (200 if quick else 1000), quick=quick,
                                  rt_priority=rt_priority)
    try:
        result = sweep.run(settings, progress)
    except BenchError as exc:
        typer.echo(f"benchmarks.evaluation: error: {exc}", err=True)
        raise typer.Exit(1) from None
    command = ["python", "-m", "benchmarks.evaluation", "--out", str(out)]
    command += ["--quick"] if quick else []
    command += ["--count", str(count)] if count else []
    command += ["--rt-priority", str(rt_priority)] if rt_priority != 5 else []
    figures = out.parent / "figures" / "evaluation"
    command += ["--results", str(results)] if results != RESULTS / "evaluation" else []
    evaluation_report.write(result, settings, command, out, figures, results)
    typer.echo(f"wrote {out}, {figures}/ and {results}/")


if __name__ == "__main__":
    app()
