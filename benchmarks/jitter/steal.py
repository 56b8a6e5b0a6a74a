"""Comparing a pattern with the reference runs that lost as much time to the hypervisor.

On a virtual machine a run's p99 jitter is set mostly by *steal*: the time the host ran
something else while the loop's vCPU wanted to run (``/proc/stat``). In the session-4 run the
rank correlation between a run's steal and its p99 was 0.98 over 261 runs; no coupling
pattern can win back time during which its CPU did not exist. Pairing a pattern with the
reference runs next to it in time cancels only the part of that noise that drifts slowly.

This module compares each pattern run with the reference runs of the same benchmark run
whose steal was closest to its own (the median p99 of the ``k`` nearest, ``k`` the square
root of the number of reference runs, at least 3). What is left is what the pattern itself
adds at a given amount of host interference. The interval resamples the pattern's runs *and*
the reference runs, so a thin reference curve widens it.

What it cannot see: a pattern that draws more steal onto the loop's CPU, for instance by
keeping the other vCPU busy on an oversubscribed host. The report therefore also gives the
pattern's steal minus that of the reference runs next to it (*d steal*), which shows it.
"""

from __future__ import annotations

import bisect
import math
import random
import statistics
from collections.abc import Sequence

from benchmarks.jitter.config import BOOTSTRAP_RESAMPLES, RunStats, percentile_interval

Measured = tuple[float, float]
"""(steal ms, p99 us) of one run."""


def measured(runs: Sequence[RunStats]) -> list[Measured]:
    """The runs that recorded their steal, as (steal, p99); older runs did not."""
    return [(r.steal_ms, r.p99_us) for r in runs if r.steal_ms is not None]


def neighbours(count: int) -> int:
    """How many reference runs stand for one steal value: sqrt(count), at least 3."""
    return max(3, math.isqrt(count))


def matched_deltas(runs: Sequence[Measured], refs: Sequence[Measured]) -> list[float]:
    """p99 of each run minus the median p99 of the reference runs with the nearest steal."""
    if not refs:
        return []
    ordered = sorted(refs)
    steals = [s for s, _ in ordered]
    k = min(neighbours(len(ordered)), len(ordered))
    out = []
    for steal, p99 in runs:
        # the k nearest form a window around the insertion point: widen it to the closer side
        low = high = bisect.bisect_left(steals, steal)
        while high - low < k:
            left_closer = high >= len(ordered) or steal - steals[low - 1] <= steals[high] - steal
            if low > 0 and left_closer:
                low -= 1
            else:
                high += 1
        out.append(p99 - statistics.median(p for _, p in ordered[low:high]))
    return out


def matched_delta(groups: Sequence[tuple[Sequence[Measured], Sequence[Measured]]]) -> float:
    """Median of :func:`matched_deltas` pooled over ``(runs, refs)`` groups (one per run)."""
    deltas = [d for runs, refs in groups for d in matched_deltas(runs, refs)]
    return statistics.median(deltas) if deltas else math.nan


def matched_ci(groups: Sequence[tuple[Sequence[Measured], Sequence[Measured]]],
               level: float = 0.9, resamples: int = BOOTSTRAP_RESAMPLES // 4, seed: int = 0
               ) -> tuple[float, float]:
    """Percentile-bootstrap interval of :func:`matched_delta`; runs and refs both resampled.

    Each group keeps its own reference runs: a run is matched only with references measured
    on the same host in the same benchmark run.
    """
    usable = [(runs, refs) for runs, refs in groups if runs and refs]
    if not usable:
        return math.nan, math.nan
    rng = random.Random(seed)
    medians = []
    for _ in range(resamples):
        pooled: list[float] = []
        for runs, refs in usable:
            pooled += matched_deltas(rng.choices(runs, k=len(runs)),
                                     rng.choices(refs, k=len(refs)))
        medians.append(statistics.median(pooled))
    return percentile_interval(medians, level)
