"""``python -m benchmarks.jitter``: HRT loop jitter per coupling pattern (thesis 5.3), GIL study.

The modules of the benchmark:

* :mod:`~benchmarks.jitter.config`: scenarios, the run's configuration, the statistics
  (medians over rounds, pairing with the same round's reference, the target);
* :mod:`~benchmarks.jitter.runner`: the server, publisher, stress and worker processes
  around a run, and the rounds;
* :mod:`~benchmarks.jitter.worker`: one scenario in one process (and the publisher);
* :mod:`~benchmarks.jitter.shm`: the GIL study's hand-built separate-process loop
  (``shm-1000``; the pattern suite measures the patterns' own process layout instead);
* :mod:`~benchmarks.jitter.report`: markdown and plot;
* :mod:`~benchmarks.jitter.steal`: the comparison at equal host steal time;
* :mod:`~benchmarks.jitter.pool`: several runs' JSON pooled (``... jitter pool``);
* this module: :func:`run` and ``python -m benchmarks.jitter`` (``run`` measures; ``worker``,
  ``publisher``, ``switch-cost`` and ``pool`` are the helper processes and the pooling).

Suites: ``patterns`` (the thesis figures 5.8-5.10, every proper pattern in its default layout,
the loop in its own process, and in-process) and
``gil`` (the loop next to the SDK's threads at 100 Hz and 1 kHz traffic, a pure-Python thread,
a ``sendto`` thread, for several ``sys.setswitchinterval`` values, the SDK threads at a
real-time priority, and the loop in its own process: see docs/gil.md).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Annotated

import typer

from benchmarks import RESULTS
from benchmarks.jitter.config import (
    TOPIC_IN,
    JitterConfig,
    RunStats,
    Scenario,
    ScenarioResult,
    gil_scenarios,
    percentile,
    target_ok,
)
from benchmarks.jitter.pool import pooled_deltas
from benchmarks.jitter.report import (
    machine_info,
    plot_results,
    render_markdown,
    write_section,
)
from benchmarks.jitter.runner import exit_on_signals, run_suite

__all__ = ["JitterConfig", "RunStats", "Scenario", "ScenarioResult", "command_line",
           "gil_scenarios", "main", "percentile", "pooled_deltas", "run", "target_ok",
           "write_section"]


def run(config: JitterConfig, progress: Callable[[str], None] = print
        ) -> list[ScenarioResult]:
    """Measure, then write the plot and the markdown section when asked to."""
    machine = machine_info()
    with exit_on_signals():
        results = run_suite(config, progress)
    machine["load_after"] = machine_info()["load"]
    if config.plot is not None:
        plot_results(config, results, config.plot)
    section = render_markdown(config, results, machine, config.plot)
    if config.out is not None:
        title = "HRT loop jitter per coupling pattern" if config.suite == "patterns" \
            else "The GIL and the HRT loop"
        write_section(config.out, section, title, config.markers())
        raw = (config.results or config.out.parent) / f"{config.out.stem}.{config.key}.json"
        raw.write_text(json.dumps({
            "config": {k: str(v) for k, v in asdict(config).items()},
            "machine": machine,
            "results": [{"scenario": asdict(r.scenario), "runs": [asdict(s) for s in r.runs],
                         "info": r.info} for r in results],
        }, indent=1))
    progress(section)
    return results


# -- python -m benchmarks.jitter {worker,publisher,pool} --------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.jitter")
    sub = parser.add_subparsers(dest="role", required=True)
    worker = sub.add_parser("worker", help="run one scenario (spawned by the benchmark)")
    worker.add_argument("--scenario", required=True)
    worker.add_argument("--port", type=int, required=True)
    worker.add_argument("--cycles", type=int, default=5000)
    worker.add_argument("--period", type=float, default=0.001)
    worker.add_argument("--switch-interval", type=float, default=None)
    worker.add_argument("--no-priority", dest="priority", action="store_false")
    worker.add_argument("--cpu", type=int, default=None, help="pin the loop thread")
    worker.add_argument("--no-mlock", dest="mlock", action="store_false")
    worker.add_argument("--result", required=True)
    pub = sub.add_parser("publisher", help="publish a sine at a rate, for a bounded time")
    pub.add_argument("--host", default="127.0.0.1")
    pub.add_argument("--port", type=int, required=True)
    pub.add_argument("--topic", default=TOPIC_IN)
    pub.add_argument("--rate", type=float, default=100.0)
    pub.add_argument("--seconds", type=float, default=60.0)
    sub.add_parser("switch-cost", help="what a short GIL switch interval costs CPU-bound threads")
    pool = sub.add_parser("pool", help="pool the paired and equal-steal differences of several "
                                       "runs' JSON")
    pool.add_argument("json", nargs="+", type=Path)
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the helper processes."""
    args = _parser().parse_args(argv)
    if args.role == "worker":
        if args.switch_interval is not None:
            sys.setswitchinterval(args.switch_interval)
        if args.scenario.startswith("shm-"):  # the loop in its own process, fed through shm
            from benchmarks.jitter.shm import shm_parent

            Path(args.result).write_text(json.dumps(shm_parent(args)))
        else:
            from benchmarks.jitter.worker import worker_main

            worker_main(args)
    elif args.role == "publisher":
        from benchmarks.jitter.worker import publisher_main

        publisher_main(args)
    elif args.role == "switch-cost":
        from benchmarks.jitter.worker import switch_cost

        print(switch_cost())
    else:
        try:
            print(pooled_deltas(args.json))
        except (OSError, ValueError) as exc:
            raise SystemExit(f"pool: {exc}") from None


def command_line(argv: Sequence[str]) -> str:
    """The command as typed, for the report."""
    return "python -m benchmarks.jitter " + shlex.join(argv)


# -- python -m benchmarks.jitter run (the measurement) -------------------------------------

app = typer.Typer(help="HRT loop jitter per coupling pattern, and the GIL study.",
                  add_completion=False, no_args_is_help=True)


@app.command("run")
def run_command(
    suite: Annotated[str, typer.Option(help="patterns (thesis 5.3) or gil (docs/gil.md).")]
    = "patterns",
    cycles: Annotated[int, typer.Option(help="Deadlines per run.")] = 5000,
    period_us: Annotated[int, typer.Option("--period-us", help="Loop period.")] = 1000,
    repeats: Annotated[int, typer.Option(help="Rounds; figures are medians over them.")] = 5,
    stress: Annotated[bool, typer.Option(help="Run `stress --cpu 2 --io 2 --hdd 1` meanwhile.")]
    = False,
    publish_hz: Annotated[float, typer.Option(help="Rate of the set-point publisher.")] = 100.0,
    only: Annotated[str, typer.Option(help="Comma-separated scenarios (plus the reference).")]
    = "",
    priority: Annotated[bool, typer.Option("--rt/--no-rt",
                                           help="PriParallel priorities for the loop.")] = True,
    cpu: Annotated[int | None, typer.Option(
        help="Pin every loop (the reference's too) to this CPU; default the last, -1 none.")]
    = None,
    isolate: Annotated[bool, typer.Option(
        help="Keep server, publishers and SDK threads off the loops' CPU.")] = True,
    mlock: Annotated[bool, typer.Option(help="mlockall in every loop process.")] = True,
    interleave: Annotated[bool, typer.Option(
        help="Patterns suite: run the reference between every two scenarios and compare each "
             "with its neighbours (about twice the time per round).")] = True,
    out: Annotated[Path, typer.Option(help="Markdown file the figures are written to.")]
    = Path("benchmarks/results/jitter.md"),
    plot: Annotated[Path, typer.Option(help="PNG of the jitter per cycle.")]
    = Path("docs/figures/jitter.png"),
    results: Annotated[Path, typer.Option(help="Directory of the raw runs' JSON.")] = RESULTS,
) -> None:
    """HRT loop jitter per coupling pattern, next to a reference loop from the same run.

    Writes OUT's section, PLOT, and the raw runs to RESULTS/<out stem>.<suite>.json.
    """
    if suite not in ("patterns", "gil"):
        raise typer.BadParameter("--suite must be 'patterns' or 'gil'")
    if cpu is None:
        cpu = (os.cpu_count() or 1) - 1
    run(JitterConfig(suite=suite, cycles=cycles, period=period_us / 1e6,  # type: ignore[arg-type]
                     repeats=repeats, stress=stress, publish_hz=publish_hz,
                     only=tuple(s for s in only.split(",") if s), priority=priority,
                     cpu=None if cpu < 0 else cpu, isolate=isolate, mlock=mlock,
                     interleave=interleave, out=out, plot=plot, results=results,
                     command=command_line(sys.argv[1:])), typer.echo)


_PASS_THROUGH = {"allow_extra_args": True, "ignore_unknown_options": True}


def _helper(name: str, summary: str) -> None:
    """``name`` as a command of :data:`app` whose arguments go to :func:`main`'s parser."""

    @app.command(name, help=summary, context_settings=_PASS_THROUGH, add_help_option=False)
    def helper(ctx: typer.Context) -> None:
        main([name, *ctx.args])


_helper("worker", "One scenario in this process (spawned by `run`; --help for its options).")
_helper("publisher", "Publish a sine at a rate, for a bounded time.")
_helper("switch-cost", "What a short GIL switch interval costs CPU-bound threads.")
_helper("pool", "Pool the paired and equal-steal differences of several runs' JSON.")


if __name__ == "__main__":
    app()
