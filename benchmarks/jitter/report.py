"""The report of a ``python -m benchmarks.jitter run``: markdown section, plot, pooled rounds."""

from __future__ import annotations

import contextlib
import datetime as dt
import math
import os
import platform
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.jitter.config import (
    GIL_BASE,
    GIL_INTERVALS,
    JitterConfig,
    ScenarioResult,
    allowance,
    interval_label,
    judge,
)
from benchmarks.jitter.steal import matched_ci, matched_delta, measured


def machine_info() -> dict[str, str]:
    """What the figures were measured on."""
    cpu = "unknown"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    load = "unknown"
    with contextlib.suppress(OSError):
        load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
    return {
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "host": f"{platform.system()} {platform.release()} {platform.machine()}",
        "cpu": f"{cpu}, {os.cpu_count()} CPUs",
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "load": load,
    }



def render_markdown(config: JitterConfig, results: list[ScenarioResult],
                    machine: dict[str, str], plot: Path | None) -> str:
    """The generated section of docs/jitter.md or docs/gil.md."""
    begin, end = config.markers()
    lines = [
        begin,
        f"Command: `{config.command or 'python -m benchmarks.jitter run'}`",
        "",
        f"Measured {machine['date']} on {machine['host']}, {machine['cpu']}, "
        f"{machine['python']}; load average before the run {machine['load']}, after "
        f"{machine.get('load_after', 'unknown')}. {config.cycles} deadlines of a "
        f"{config.period * 1e6:g} us loop per run, {config.repeats} rounds, stress "
        f"{'on' if config.stress else 'off'}. Every loop (the reference's too): "
        f"{_treatment(results)}; server, publishers and the workers' other threads "
        f"{'kept off the loop CPU' if config.isolate and config.cpu is not None else 'anywhere'}.",
        "",
        "Figures are medians over the runs of each run's p50 / p99 / max of the absolute "
        "jitter |release - deadline| in microseconds. " + _pairing(config) + " *d p99* is "
        "the median over the rounds of (p99 - reference p99), *p99/ref* the median of their "
        "ratio, *rounds met* in how many rounds p99 <= max(1.1 x, +20 us) of that "
        "reference. *90 % CI*: a bootstrap interval of d p99 (rounds resampled). *target*: "
        "d p99 <= max(10 % of the reference's median p99, 20 us); *met* or *missed* when the "
        "whole interval is on one side of that, *unresolved* when the run cannot tell. "
        "*missed* (column): releases skipped because the loop was still busy (median per "
        "run). *steal ms*: time the hypervisor took from the loop's CPU while the loop ran "
        "(median per run, /proc/stat; 10 ms resolution).",
        "",
        "| group | scenario | p50 us | p99 us | max us | missed | steal ms | d p99 us "
        "| 90 % CI us | p99/ref | rounds met | target |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    refs = {r.scenario.group: r for r in results if r.scenario.name == "reference"}
    default_ref = next((r for r in results if r.scenario.name == "reference"), None)
    for res in results:
        ref = refs.get(res.scenario.group, default_ref)
        paired = ["", "", "", "", ""]
        if ref is not None and res is not ref:
            delta = res.paired_delta(ref)
            low, high = res.delta_ci(ref)
            met, rounds = res.rounds_met(ref)
            verdict = res.verdict(ref)
            if "naive" in res.scenario.name:
                # p99 of a naive receive is capped at one period (late releases are
                # skipped, see "missed"): the target is for the proper patterns only
                verdict = "n/a (naive)"
            paired = [f"{delta:+.0f}", f"{low:+.0f} .. {high:+.0f}",
                      f"{res.paired_ratio(ref):.2f}", f"{met}/{rounds}", verdict]
        lines.append(
            f"| {res.scenario.group} | {res.scenario.label} | {res.median('p50_us'):.0f} | "
            f"{res.median('p99_us'):.0f} | {res.median('max_us'):.0f} | "
            f"{res.median('missed'):.0f} | {_median_steal(res)} | " + " | ".join(paired)
            + " |")
    lines += _steal_table(results, lambda res: refs.get(res.scenario.group, default_ref))
    lines += ["", "Per round (p99 us; where a round ran a scenario more than once, the "
              "median of its runs and their number):", "",
              "| scenario | " + " | ".join(f"round {i + 1}" for i in range(config.repeats))
              + " |", "|---|" + "---:|" * config.repeats]
    for res in results:
        by_round = _per_round_p99(res)
        cells = " | ".join(by_round.get(i, "failed") for i in range(config.repeats))
        lines.append(f"| {res.scenario.group}: {res.scenario.name} | {cells} |")
    if plot is not None:
        rel = plot.name if config.out is None else os.path.relpath(plot, config.out.parent)
        lines += ["", f"![absolute jitter per cycle]({rel})"]
    lines.append(end)
    return "\n".join(lines) + "\n"


def _steal_table(results: list[ScenarioResult],
                 ref_of: Callable[[ScenarioResult], ScenarioResult | None]) -> list[str]:
    """Each scenario against the reference runs with the same steal (:mod:`.jitter_steal`)."""
    rows = []
    for res in results:
        ref = ref_of(res)
        if ref is None or res is ref:
            continue
        groups = [(measured(res.runs), measured(ref.runs))]
        if not (groups[0][0] and groups[0][1]):
            continue
        low, high = matched_ci(groups)
        d_steal = res.paired(ref, lambda mine, theirs: mine - theirs, "steal_ms")
        verdict = ("n/a (naive)" if "naive" in res.scenario.name
                   else judge(low, high, allowance(ref.median("p99_us"))))
        rows.append(f"| {res.scenario.group} | {res.scenario.label} | {_median_steal(res)} | "
                    f"{statistics.median(d_steal) if d_steal else math.nan:+.0f} | "
                    f"{matched_delta(groups):+.0f} | {low:+.0f} .. {high:+.0f} | {verdict} |")
    if not rows:
        return []
    return ["", "At equal steal: each run compared with the reference runs of this run whose "
            "steal was closest to its own (the median p99 of the sqrt(n) nearest), which "
            "takes the host's interference out of the comparison (`benchmarks."
            "jitter.steal`; interval: runs and reference runs resampled; same allowance). "
            "*d steal*: the scenario's steal minus that of the reference runs next to it "
            "(median); near zero, the pattern does not draw more host interference onto the "
            "loop's CPU than the loop alone.", "",
            "| group | scenario | steal ms | d steal ms | d p99 at equal steal us | 90 % CI us "
            "| target |", "|---|---|---:|---:|---:|---|---|", *rows]


def _pairing(config: JitterConfig) -> str:
    if config.interleave and config.suite == "patterns":
        return ("Each round ran the reference before every scenario and once more at the "
                "end; each scenario is paired with the mean of the two reference runs next "
                "to it (seconds apart, so the host's drifting load mostly cancels).")
    return ("Each scenario is paired with the reference measured in the same round (which "
            "cancels the load that drifts between rounds).")


def _median_steal(res: ScenarioResult) -> str:
    steal = [r.steal_ms for r in res.runs if r.steal_ms is not None]
    return f"{statistics.median(steal):.0f}" if steal else "n/a"


def _per_round_p99(res: ScenarioResult) -> dict[int, str]:
    rounds: dict[int, list[float]] = {}
    for run in res.runs:
        rounds.setdefault(run.round, []).append(run.p99_us)
    return {rnd: f"{values[0]:.0f}" if len(values) == 1
            else f"{statistics.median(values):.0f} ({len(values)})"
            for rnd, values in rounds.items()}


def _treatment(results: list[ScenarioResult]) -> str:
    """What every loop process got, as recorded from inside the loops."""
    def seen(key: str) -> str:
        values = sorted({str(i.get(key, "unknown")) for r in results for i in r.info})
        return " / ".join(values) if values else "unknown"

    return (f"HRT thread {seen('policy')}, on CPU {seen('cpus')}, mlockall {seen('mlockall')}, "
            f"timer slack {seen('timer_slack')}")


def write_section(path: Path, section: str, title: str, markers: tuple[str, str]) -> None:
    """Replace the generated section of ``path``, keeping the prose around it."""
    begin, end = markers
    if path.exists():
        text = path.read_text()
        if begin in text and end in text:
            head, rest = text.split(begin, 1)
            tail = rest.split(end, 1)[1]
            path.write_text(head + section.rstrip("\n") + tail)
            return
        path.write_text(text.rstrip("\n") + "\n\n" + section)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {title}\n\n{section}")


def _median_run(res: ScenarioResult) -> int:
    """Index of the run with the median p99."""
    order = sorted(range(len(res.runs)), key=lambda i: res.runs[i].p99_us)
    return order[len(order) // 2] if order else 0


def _run_in_round(res: ScenarioResult, rnd: int) -> int:
    """Index of ``res``'s (first) run in round ``rnd``, or its last run if it has none there."""
    return next((i for i, r in enumerate(res.runs) if r.round == rnd), len(res.runs) - 1)


def plot_results(config: JitterConfig, results: list[ScenarioResult], path: Path) -> None:
    """Absolute jitter per cycle, one panel per group (thesis figures 5.8-5.10 style)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = next((r for r in results if r.scenario.name == "reference"), None)
    groups: list[str] = []
    for res in results:
        if res.scenario.name != "reference" and res.scenario.group not in groups:
            groups.append(res.scenario.group)
    if config.suite == "gil":
        _plot_gil(plt, results, path)
        return
    fig, axes = plt.subplots(len(groups), 1, figsize=(10, 3.2 * len(groups)), squeeze=False)
    ref_run = _median_run(ref) if ref is not None and ref.runs else None
    rnd = ref.runs[ref_run].round if ref is not None and ref_run is not None else 0
    for ax, group in zip(axes[:, 0], groups, strict=True):
        members = ([ref] if ref is not None else []) + [
            r for r in results if r.scenario.group == group and r.scenario.name != "reference"]
        for res in members:
            if not res.runs:
                continue
            index = ref_run if res is ref and ref_run is not None else _run_in_round(res, rnd)
            samples = res.lateness[index]
            stats = res.runs[index]
            ax.plot(range(len(samples)), [max(s / 1e3, 0.1) for s in samples],
                    ".", markersize=1.5,
                    label=f"{res.scenario.label} (p99 {stats.p99_us:.0f} us, "
                          f"max {stats.max_us:.0f} us)")
        ax.set_yscale("log")
        ax.set_ylabel("absolute jitter [us]")
        ax.set_title(f"{group}: {config.period * 1e6:g} us loop"
                     f"{', stressed' if config.stress else ''} (round {rnd + 1})")
        ax.legend(loc="upper right", fontsize=7, markerscale=6)
        ax.grid(True, which="both", alpha=0.3)
    axes[-1, 0].set_xlabel("release number (a naive receive releases once per message)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_gil(plt: Any, results: list[ScenarioResult], path: Path) -> None:
    present = {r.scenario.name for r in results}
    names = [name for name, _ in GIL_BASE if name in present]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / (len(GIL_INTERVALS) + 1)
    for k, interval in enumerate(GIL_INTERVALS):
        label = interval_label(interval)
        p99 = []
        p50 = []
        for name in names:
            res = next((r for r in results if r.scenario.name == name
                        and r.scenario.switch_interval == interval), None)
            p99.append(res.median("p99_us") if res else math.nan)
            p50.append(res.median("p50_us") if res else math.nan)
        xs = [i + k * width for i in range(len(names))]
        ax.bar(xs, p99, width, label=f"p99, {label}", alpha=0.85)
        ax.scatter(xs, p50, marker="_", color="black", s=80, zorder=3)
    extras = [r for r in results if r.scenario.name in ("sdk-1000-rtio", "shm-1000")]
    ticks = [i + width for i in range(len(names))]
    for j, res in enumerate(extras):
        x = len(names) + j
        ax.bar([x], [res.median("p99_us")], width * 2, color=("tab:purple", "tab:red")[j % 2],
               label=f"p99, {res.scenario.label} (switch 5 ms)")
        ax.scatter([x], [res.median("p50_us")], marker="_", color="black", s=80, zorder=3)
        ticks.append(x)
    ax.set_xticks(ticks, names + [r.scenario.name for r in extras], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("absolute jitter [us] (bar p99, tick p50)")
    ax.set_title("1 kHz loop next to other threads in one interpreter")
    ax.legend(fontsize=7)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
