"""Statistics over measured samples, shared by the children and the reports.

NaN stands for "not measured" (a skipped repeat, an empty phase) and passes through, so a
table shows ``-`` instead of a made-up figure.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence


def percentile(sorted_values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (0..100) of already sorted values; NaN when empty."""
    if not sorted_values:
        return math.nan
    pos = (len(sorted_values) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (pos - lo)


def median(values: Sequence[float]) -> float:
    """Median ignoring NaN (a skipped repeat); NaN when nothing is left."""
    kept = [v for v in values if not math.isnan(v)]
    return statistics.median(kept) if kept else math.nan


def ratio(value: float, base: float) -> float:
    """``value / base``, NaN when either was not measured (or the base is zero)."""
    return value / base if base and not math.isnan(base) and not math.isnan(value) else math.nan
