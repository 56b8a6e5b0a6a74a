"""``python -m benchmarks.jitter pool A.json B.json ...``: several runs read as one.

One run's rounds cannot separate a 200 us effect from a machine whose reference p99 swings by
milliseconds between rounds; the same condition measured in several runs can. Each run's
scenarios are compared with that run's own reference runs only (same-round pairing, and, for
runs that recorded steal, the steal-matched comparison of :mod:`.jitter_steal`); the
differences are then pooled.
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
from collections.abc import Sequence
from pathlib import Path

from benchmarks.jitter.config import (
    RunStats,
    Scenario,
    ScenarioResult,
    allowance,
    bootstrap_median_ci,
    judge,
)
from benchmarks.jitter.steal import Measured, matched_ci, matched_delta, measured

__all__ = ["pooled_deltas", "results_from_json"]


def results_from_json(path: Path, round_offset: int = 0) -> list[ScenarioResult]:
    """The scenarios and runs of a run's JSON (rounds shifted so that files do not mix).

    Raises ``ValueError`` naming the file when it is not such a result (``OSError`` when it
    cannot be read).
    """
    out = []
    try:
        for raw in json.loads(path.read_text())["results"]:
            res = ScenarioResult(Scenario(**raw["scenario"]))
            for run in raw["runs"]:
                stats = RunStats.from_json(run)
                res.runs.append(dataclasses.replace(stats, round=stats.round + round_offset))
            out.append(res)
    except (ValueError, KeyError, TypeError) as exc:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: not the JSON of a `python -m benchmarks.jitter run` run "
                         f"({type(exc).__name__}: {exc})") from None
    return out


def pooled_deltas(paths: Sequence[Path]) -> str:
    """A markdown table of the pooled differences to each run's own reference.

    Per scenario: median difference of p50 and p99 with a bootstrap interval of the latter,
    in how many rounds the p99 was worse than the reference's, the verdict against the target
    (allowance from the pooled reference's median p99), and, where the runs recorded steal,
    the difference at equal steal with its interval and verdict.
    """
    pool: dict[tuple[str, str], tuple[list[float], list[float]]] = {}
    steal: dict[tuple[str, str], list[tuple[list[Measured], list[Measured]]]] = {}
    ref_p99: list[float] = []
    for number, path in enumerate(paths):
        results = results_from_json(path, round_offset=1000 * number)
        refs = {r.scenario.switch_interval: r for r in results
                if r.scenario.name == "reference"}
        if None in refs:
            ref_p99 += [run.p99_us for run in refs[None].runs]
        for res in results:
            ref = refs.get(res.scenario.switch_interval, refs.get(None))
            if res.scenario.name == "reference" or ref is None:
                continue
            key = (res.scenario.name, res.scenario.group)
            d50, d99 = pool.setdefault(key, ([], []))
            d50 += res.paired(ref, lambda mine, theirs: mine - theirs, "p50_us")
            d99 += res.paired(ref, lambda mine, theirs: mine - theirs)
            steal.setdefault(key, []).append((measured(res.runs), measured(ref.runs)))
    allowed = allowance(statistics.median(ref_p99)) if ref_p99 else 20.0
    lines = [f"Target allowance: +{allowed:.0f} us (pooled reference median p99 "
             f"{statistics.median(ref_p99) if ref_p99 else math.nan:.0f} us).", "",
             "| scenario | group | rounds | d p50 us | d p99 us | 90 % CI us "
             "| p99 worse than ref | target | d p99 at equal steal us | 90 % CI us | target |",
             "|---|---|---:|---:|---:|---|---:|---|---:|---|---|"]
    for key, (d50, d99) in pool.items():
        name, group = key
        naive = "naive" in name
        low, high = bootstrap_median_ci(d99)
        cells = [name, group, str(len(d99)), f"{statistics.median(d50):+.0f}",
                 f"{statistics.median(d99):+.0f}", f"{low:+.0f} .. {high:+.0f}",
                 f"{sum(1 for d in d99 if d > 0)}/{len(d99)}",
                 "n/a (naive)" if naive else judge(low, high, allowed)]
        groups = [g for g in steal[key] if g[0] and g[1]]
        if groups:
            s_low, s_high = matched_ci(groups)
            cells += [f"{matched_delta(groups):+.0f}", f"{s_low:+.0f} .. {s_high:+.0f}",
                      "n/a (naive)" if naive else judge(s_low, s_high, allowed)]
        else:
            cells += ["not recorded", "", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
