"""``rlbridge bench jitter``: HRT loop jitter per coupling pattern (thesis 5.3) and the GIL study.

The modules of the benchmark:

* :mod:`~rlbridge.bench.jitter_config`: scenarios, the run's configuration, the statistics
  (medians over rounds, pairing with the same round's reference, the target);
* :mod:`~rlbridge.bench.jitter_runner`: the server, publisher, stress and worker processes
  around a run, and the rounds;
* :mod:`~rlbridge.bench.jitter_worker`: one scenario in one process (and the publisher);
* :mod:`~rlbridge.bench.jitter_shm`: the GIL study's hand-built separate-process loop
  (``shm-1000``; the pattern suite measures the patterns' own process layout instead);
* :mod:`~rlbridge.bench.jitter_report`: markdown and plot;
* :mod:`~rlbridge.bench.jitter_steal`: the comparison at equal host steal time;
* :mod:`~rlbridge.bench.jitter_pool`: several runs' JSON pooled (``... jitter pool``);
* this module: :func:`run` (what the CLI calls) and ``python -m rlbridge.bench.jitter``, the
  entry point of the helper processes.

Suites: ``patterns`` (the thesis figures 5.8-5.10, every proper pattern in its default layout,
the loop in its own process, and in-process) and
``gil`` (the loop next to the SDK's threads at 100 Hz and 1 kHz traffic, a pure-Python thread,
a ``sendto`` thread, for several ``sys.setswitchinterval`` values, the SDK threads at a
real-time priority, and the loop in its own process: see docs/gil.md).
"""

from __future__ import annotations

import argparse
import json
import shlex
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

from rlbridge.bench.jitter_config import (
    TOPIC_IN,
    JitterConfig,
    RunStats,
    Scenario,
    ScenarioResult,
    gil_scenarios,
    percentile,
    target_ok,
)
from rlbridge.bench.jitter_pool import pooled_deltas
from rlbridge.bench.jitter_report import (
    machine_info,
    plot_results,
    render_markdown,
    write_section,
)
from rlbridge.bench.jitter_runner import exit_on_signals, run_suite

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
        raw = config.out.with_name(f"{config.out.stem}.{config.key}.json")
        raw.write_text(json.dumps({
            "config": {k: str(v) for k, v in asdict(config).items()},
            "machine": machine,
            "results": [{"scenario": asdict(r.scenario), "runs": [asdict(s) for s in r.runs],
                         "info": r.info} for r in results],
        }, indent=1))
    progress(section)
    return results


# -- python -m rlbridge.bench.jitter {worker,publisher,pool} --------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m rlbridge.bench.jitter")
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
        from rlbridge.bench.jitter_worker import worker_main

        worker_main(args)
    elif args.role == "publisher":
        from rlbridge.bench.jitter_worker import publisher_main

        publisher_main(args)
    elif args.role == "switch-cost":
        from rlbridge.bench.jitter_worker import switch_cost

        print(switch_cost())
    else:
        try:
            print(pooled_deltas(args.json))
        except (OSError, ValueError) as exc:
            raise SystemExit(f"pool: {exc}") from None


def command_line(argv: Sequence[str]) -> str:
    """The command as typed, for the report."""
    return "rlbridge " + shlex.join(argv)


if __name__ == "__main__":
    main()
