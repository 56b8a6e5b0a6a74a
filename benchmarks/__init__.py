"""Research benchmark suites of rlbridge, run from a checkout of the repository.

What ships in the package (``rlbridge bench latency|throughput|load|ros2``) measures a user's
own machine and link. What lives here is the research behind the design and its documents:

* :mod:`benchmarks.jitter`: HRT loop jitter per coupling pattern and the GIL study
  (docs/jitter.md, docs/gil.md): ``python -m benchmarks.jitter --help``;
* :mod:`benchmarks.evaluation`: every network scenario of the thesis, rlbridge next to ZeroMQ
  and Zenoh across the emulated link (docs/evaluation.md): ``python -m benchmarks.evaluation``;
* :mod:`benchmarks.soak`: the load benchmark held for minutes (docs/load.md);
* :mod:`benchmarks.channels`, :mod:`benchmarks.policy_costs`, :mod:`benchmarks.redundancy`:
  micro-benchmarks of the CSP layer and the channel policies (docs/bench-channels.md,
  docs/policies.md);
* single scripts: ``bench_seal.py``, ``failsafe_read.py``, ``server_path_ab.py``.

Raw results (JSON, CSV) are written to ``benchmarks/results/``; the markdown and the figures
the prose shows go to ``docs/`` and ``docs/figures/``. Run every command from the repository's
root (``python -m benchmarks.<suite>``); the suites import the installed ``rlbridge``, never
the other way round.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
"""The repository's root: where ``python -m benchmarks...`` finds this package."""

RESULTS = ROOT / "benchmarks" / "results"
"""Where the suites write their raw results."""


def module_argv(module: str, *args: str) -> list[str]:
    """argv running ``python -m module args`` in a child process, whatever its cwd.

    The suites are not installed, so a child finds them through the repository's root.
    """
    boot = (f"import runpy, sys; sys.path.insert(0, {str(ROOT)!r}); "
            f"runpy.run_module({module!r}, run_name='__main__', alter_sys=True)")
    return [sys.executable, "-c", boot, *args]
