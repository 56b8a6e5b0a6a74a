"""Two source trees measured in turn (ABBA...), for the ``*_ab.py`` scripts.

A and B alternate, so a change in the machine's load hits both alike; the figure is each side's
median, and B/A next to the load average it was measured under. A script is run as a file
(``python benchmarks/x_ab.py``), so it puts the checkout's root on ``sys.path`` before it
imports this module (:func:`importable`).
"""

from __future__ import annotations

import os
import statistics
from collections.abc import Callable


def interleave(run: Callable[[str], tuple[float, str]], a: str, b: str, repeats: int,
               digits: int, unit: str = "µs/value") -> dict[str, list[float]]:
    """``run`` each tree ``repeats`` times, A and B alternating (ABBA...): every run as it
    ends (its figure in ``unit`` and ``run``'s detail), then the medians and B/A. Returns
    every run's figure per side."""
    results: dict[str, list[float]] = {"A": [], "B": []}
    for i in range(repeats):
        for name in ("A", "B") if i % 2 == 0 else ("B", "A"):
            figure, detail = run(a if name == "A" else b)
            results[name].append(figure)
            print(f"{name} {figure:6.{digits}f} {unit} {detail}", flush=True)
    med = {k: statistics.median(v) for k, v in results.items()}
    for k, v in results.items():
        print(f"{k} median {med[k]:.{digits}f} {unit}  runs {[round(x, digits) for x in v]}")
    print(f"B/A {med['B'] / med['A']:.2f}  load average {os.getloadavg()}")
    return results
