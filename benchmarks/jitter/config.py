"""What a ``python -m benchmarks.jitter run`` run measures and how a run's figures are reduced.

Scenarios (the rows), the run's configuration (built by the CLI), and the statistics: per run
p50 / p99 / max of the absolute jitter; per scenario the median over the rounds, and the
comparison with the reference *measured in the same round* (difference, ratio, and in how
many rounds the target held), which is what survives a shared, noisy machine. With
``interleave`` (the pattern suite's default) the reference runs between every two scenarios and
each scenario is compared with the two reference runs next to it, seconds apart instead of a
round (minutes) apart.
"""

from __future__ import annotations

import math
import random
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

F64 = "std_msgs/msg/Float64"
TOPIC_IN = "/bench/setpoint"
TOPIC_IN_FAST = "/bench/setpoint_fast"
TOPIC_OUT = "/bench/output"

Suite = Literal["patterns", "gil"]


@dataclass(frozen=True)
class Scenario:
    """One measured configuration: a pattern or a GIL-study condition."""

    name: str
    group: str
    label: str
    switch_interval: float | None = None  # None: CPython's default (5 ms)


PROCESS_SUFFIX = "-process"
"""Scenario names ending in this run the pattern's default layout: the loop in its own process."""

_PROPER: tuple[tuple[str, str, str], ...] = (
    ("receive-nonblocking", "receive", "Receive non-blocking (5.3)"),
    ("receive-blocking", "receive", "Receive blocking (5.4)"),
    ("send-buffered", "send", "Send buffered (5.5)"),
    ("send-sampled", "send", "Send sampled (5.6)"),
    ("send-loop-100", "send loop", "Send loop 100 Hz (5.10)"),
    ("send-loop-1000", "send loop", "Send loop 1000 Hz (5.10)"),
)

_NAIVE: dict[str, tuple[str, str, str]] = {
    "receive": ("receive-naive", "receive", "Receive naive, in-process"),
    "send": ("send-naive", "send", "Send naive, in-process"),
}


def _pattern_scenarios() -> tuple[Scenario, ...]:
    """Per group: the proper patterns in their own process, then in-process, then naive."""
    out = [Scenario("reference", "all", "Reference")]
    for group in ("receive", "send", "send loop"):
        proper = [p for p in _PROPER if p[1] == group]
        out += [Scenario(name + PROCESS_SUFFIX, group, f"{label}, own process (default)")
                for name, group, label in proper]
        out += [Scenario(name, group, f"{label}, in-process (layout='thread')")
                for name, group, label in proper]
        if group in _NAIVE:
            out.append(Scenario(*_NAIVE[group]))
    return tuple(out)


PATTERN_SCENARIOS: tuple[Scenario, ...] = _pattern_scenarios()
"""Every proper pattern in both layouts (the in-process ones keep their old names, so runs
from before the process layout existed still pool with these); naive ones in-process only."""


GIL_BASE: tuple[tuple[str, str], ...] = (
    ("reference", "loop alone"),
    ("sdk-100", "SDK threads, 100 Hz in + out"),
    ("sdk-1000", "SDK threads, 1 kHz in + out"),
    ("sendto-1000", "thread calling sendto at 1 kHz"),
    ("pyburn", "thread running pure Python"),
)
GIL_INTERVALS: tuple[float | None, ...] = (None, 0.0005, 0.0001)


def gil_scenarios() -> tuple[Scenario, ...]:
    """Every GIL-study condition at every switch interval, plus the separate-process loop."""
    out = [
        Scenario(name, interval_label(interval), label, interval)
        for interval in GIL_INTERVALS
        for name, label in GIL_BASE
    ]
    out.append(Scenario("sdk-1000-rtio", "SDK threads real-time",
                        "SDK threads at SCHED_FIFO below the loop, 1 kHz in + out"))
    out.append(Scenario("shm-1000", "separate process",
                        "loop in its own process, shared memory, 1 kHz in + out"))
    return tuple(out)


def interval_label(interval: float | None) -> str:
    if interval is None:
        return "switch 5 ms (default)"
    return f"switch {interval * 1e6:g} us"


@dataclass(frozen=True)
class JitterConfig:
    """Everything a run needs; built by the CLI."""

    suite: Suite = "patterns"
    cycles: int = 5000
    period: float = 0.001
    repeats: int = 3
    stress: bool = False
    publish_hz: float = 100.0
    only: tuple[str, ...] = ()
    priority: bool = True
    cpu: int | None = None
    isolate: bool = True
    mlock: bool = True
    interleave: bool = True
    out: Path | None = None
    plot: Path | None = None
    results: Path | None = None
    """Directory of the raw runs' JSON (the CLI: benchmarks/results/); None: next to ``out``."""
    command: str = ""

    @property
    def key(self) -> str:
        """Names this run's generated section, so that variants can share one document."""
        return (f"{self.suite}{'-stress' if self.stress else ''}"
                f"{'' if self.priority else '-nort'}{'-only' if self.only else ''}")

    def markers(self) -> tuple[str, str]:
        """The comments that delimit this run's generated section of the markdown file."""
        return (f"<!-- bench:jitter:{self.key}:begin -->",
                f"<!-- bench:jitter:{self.key}:end -->")

    def scenarios(self) -> tuple[Scenario, ...]:
        chosen = PATTERN_SCENARIOS if self.suite == "patterns" else gil_scenarios()
        if self.only:
            keep = set(self.only)
            chosen = tuple(s for s in chosen if s.name in keep or s.name == "reference")
        return chosen

    def round_order(self, rnd: int) -> list[int]:
        """Indices into :meth:`scenarios` in the order round ``rnd`` runs them.

        The scenarios rotate by one place per round, so none is always first or last. With
        :attr:`interleave` the reference runs before each of them and once more at the end
        (``R S1 R S2 ... Sn R``): the host's load drifts within seconds here (docs/jitter.md),
        so the reference a round measured once cannot stand for a scenario run a minute later.
        The GIL suite has a reference per switch interval and keeps one run per round.
        """
        scenarios = self.scenarios()
        ref = next((i for i, s in enumerate(scenarios) if s.name == "reference"), None)
        interleaved = self.interleave and self.suite == "patterns" and ref is not None
        order = [i for i in range(len(scenarios)) if not (interleaved and i == ref)]
        shift = rnd % len(order) if order else 0
        order = order[shift:] + order[:shift]
        if not interleaved or ref is None:
            return order
        return [ref, *(i for index in order for i in (index, ref))]


# -- statistics ---------------------------------------------------------------------------------


def percentile(sorted_values: Sequence[int], percent: float) -> int:
    """Nearest-rank percentile of an already sorted sequence (0 when empty)."""
    if not sorted_values:
        return 0
    rank = max(0, math.ceil(percent / 100 * len(sorted_values)) - 1)
    return int(sorted_values[rank])


@dataclass(frozen=True)
class RunStats:
    """One worker run, reduced."""

    p50_us: float
    p99_us: float
    max_us: float
    samples: int
    missed: int
    round: int = 0
    seq: int | None = None
    """Position in the round's order; None in runs from before rounds were interleaved."""
    steal_ms: float | None = None
    """Time the hypervisor took from the loop's CPU during the loop (None: not measured)."""

    @classmethod
    def of(cls, lateness_ns: Sequence[int], missed: int, rnd: int = 0, seq: int | None = None,
           steal_ms: float | None = None) -> RunStats:
        ordered = sorted(lateness_ns)
        return cls(percentile(ordered, 50) / 1e3, percentile(ordered, 99) / 1e3,
                   (ordered[-1] if ordered else 0) / 1e3, len(ordered), missed, rnd, seq,
                   steal_ms)

    @classmethod
    def from_json(cls, raw: dict[str, Any]) -> RunStats:
        """A run as :func:`dataclasses.asdict` wrote it (older files lack the newer fields)."""
        known = {f: raw[f] for f in cls.__dataclass_fields__ if f in raw}
        return cls(**known)


@dataclass
class ScenarioResult:
    """All repeats of one scenario."""

    scenario: Scenario
    runs: list[RunStats] = field(default_factory=list)
    lateness: list[list[int]] = field(default_factory=list)
    info: list[dict[str, Any]] = field(default_factory=list)

    def median(self, attr: str) -> float:
        values = [float(getattr(r, attr)) for r in self.runs]
        return statistics.median(values) if values else math.nan

    def paired(self, ref: ScenarioResult, combine: Callable[[float, float], float],
               attr: str = "p99_us") -> list[float]:
        """``combine(this, reference)`` per round, for the rounds both were measured in.

        Pairing cancels the load that drifts from round to round on a shared machine. The
        reference value is the mean of the reference runs right before and after this run
        when the round was interleaved, else the mean of the round's reference runs (one,
        in a round that was not).
        """
        by_round: dict[int, list[RunStats]] = {}
        for run in ref.runs:
            if getattr(run, attr) is not None:  # steal_ms: None where not measured
                by_round.setdefault(run.round, []).append(run)
        out = []
        for run in self.runs:
            refs = by_round.get(run.round)
            if not refs or getattr(run, attr) is None:
                continue
            seq = run.seq
            near = [r for r in refs if seq is not None and r.seq is not None
                    and abs(r.seq - seq) == 1]
            theirs = statistics.fmean(float(getattr(r, attr)) for r in near or refs)
            out.append(combine(float(getattr(run, attr)), theirs))
        return out

    def paired_delta(self, ref: ScenarioResult, attr: str = "p99_us") -> float:
        """Median over rounds of (this - the reference measured in the same round)."""
        deltas = self.paired(ref, lambda mine, theirs: mine - theirs, attr)
        return statistics.median(deltas) if deltas else math.nan

    def paired_ratio(self, ref: ScenarioResult) -> float:
        """Median over rounds of (this p99 / the same round's reference p99)."""
        ratios = self.paired(ref, lambda mine, theirs: mine / theirs if theirs else math.inf)
        return statistics.median(ratios) if ratios else math.nan

    def delta_ci(self, ref: ScenarioResult, level: float = 0.9) -> tuple[float, float]:
        """A bootstrap confidence interval of :meth:`paired_delta` (rounds resampled)."""
        return bootstrap_median_ci(self.paired(ref, lambda mine, theirs: mine - theirs), level)

    def verdict(self, ref: ScenarioResult) -> str:
        """``met``, ``missed`` or ``unresolved``: the whole interval on one side of the target.

        Judging the median alone calls a coin toss a result when one round's p99 moves by an
        order of magnitude with the host's load; the interval says when the run could not tell.
        """
        low, high = self.delta_ci(ref)
        return judge(low, high, allowance(ref.median("p99_us")))

    def rounds_met(self, ref: ScenarioResult) -> tuple[int, int]:
        """(rounds in which the target held against that round's reference, rounds paired)."""
        held = self.paired(ref, lambda mine, theirs: float(target_ok(theirs, mine - theirs)))
        return int(sum(held)), len(held)


def allowance(ref_p99: float) -> float:
    """How much worse than the reference's p99 the target allows: 10 % or 20 us, the larger."""
    return max(0.1 * ref_p99, 20.0)


def judge(low: float, high: float, allowed: float) -> str:
    """The verdict on an interval of d p99: the whole of it on one side of the allowance."""
    if math.isnan(low):
        return "no rounds"
    if high <= allowed:
        return "met"
    return "missed" if low > allowed else "unresolved"


def target_ok(ref_p99: float, delta_p99: float) -> bool:
    """The target: p99 within 10 % or 20 us (whichever is larger) of the reference's."""
    return delta_p99 <= allowance(ref_p99)


BOOTSTRAP_RESAMPLES = 4000


def bootstrap_median_ci(values: Sequence[float], level: float = 0.9,
                        resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0
                        ) -> tuple[float, float]:
    """Percentile-bootstrap interval of the median of ``values`` (fixed seed: reproducible).

    Rounds are the unit that is resampled: within a round the load is shared, between
    rounds it is not, which is what the interval has to cover.
    """
    if not values:
        return math.nan, math.nan
    rng = random.Random(seed)
    n = len(values)
    return percentile_interval([statistics.median(rng.choices(values, k=n))
                                for _ in range(resamples)], level)


def percentile_interval(estimates: Sequence[float], level: float) -> tuple[float, float]:
    """The central ``level`` share of bootstrap ``estimates``: the percentile interval."""
    ordered = sorted(estimates)
    last = len(ordered) - 1
    tail = (1.0 - level) / 2
    return ordered[int(tail * last)], ordered[int((1 - tail) * last)]

