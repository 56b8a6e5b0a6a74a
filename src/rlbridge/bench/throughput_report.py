"""The report of ``rlbridge bench throughput``: rates, CPU, targets, and loss by stage."""

from __future__ import annotations

import math
from collections.abc import Sequence

from rlbridge.bench.common import fmt, markdown_table, median, ratio, report_header
from rlbridge.bench.throughput import CaseResult, Settings


def table(results: Sequence[CaseResult]) -> str:
    """Medians over repeats; ratios to the baselines of the same run."""
    base = {r.case.kind: r.rate for r in results if r.case.kind != "rlbridge" and r.runs}
    headers = ["path", "values/s", "x raw UDP", "x ZeroMQ", "x Zenoh", "lost",
               "CPU s per 1M values: sender", "server", "receiver", "total"]
    rows = []
    for r in results:
        if r.skipped is not None:
            rows.append([r.case.label, f"skipped: {r.skipped}"] + [""] * (len(headers) - 2))
            continue
        rlb = r.case.kind == "rlbridge"
        lost = median([m.lost_fraction for m in r.runs])
        rows.append([r.case.label, fmt(r.rate)]
                    + [fmt(ratio(r.rate, base.get(k, math.nan)), 2) for k in KINDS]
                    + [f"{100 * lost:.2f} %" if not math.isnan(lost) else "-",
                       fmt(r.cpu("publisher" if rlb else "sender"), 2),
                       fmt(r.cpu("server"), 2) if rlb else "-",
                       fmt(r.cpu("subscriber" if rlb else "receiver"), 2),
                       fmt(r.cpu("total"), 2)])
    return markdown_table(headers, rows)


KINDS = ("udp", "zmq", "zenoh")


def loss_table(results: Sequence[CaseResult]) -> str:
    """Where rlbridge values were lost, per repeat (UDP overload shows up here)."""
    rows = []
    for r in results:
        if r.case.kind != "rlbridge":
            continue
        for i, m in enumerate(r.runs):
            stages = ", ".join(f"{k}: {v:,}" for k, v in m.loss.items() if v)
            seen = ", ".join(f"{k}: {v:,}" for k, v in m.seen.items() if v)
            rows.append([r.case.label, str(i + 1), fmt(m.pub_rate), fmt(m.rate),
                         f"{m.written:,}", stages or "none", seen or "-"])
    return markdown_table(["path", "repeat", "written/s", "read/s", "written",
                           "lost, by stage (adds up to end to end)",
                           "seen as (not added)"], rows)


def targets(results: Sequence[CaseResult]) -> list[str]:
    """The issue's targets, each with its verdict (only rows measured in this run)."""
    by = {r.case.key: r for r in results if r.runs}
    lines = []
    rivals = [by[k] for k in ("zmq", "zenoh") if k in by]
    for key in ("rlb-tcp-batch", "rlb-udp-batch"):
        if key in by:
            r = by[key]
            ok = r.rate >= 1e6 and all(r.rate > x.rate for x in rivals)
            vs = ", ".join(f"{x.case.label} {fmt(x.rate)}" for x in rivals) or "no rivals run"
            lines.append(f"- {r.case.label}: {fmt(r.rate)} values/s; target >= 1,000,000 and "
                         f"ahead of {vs}: **{'met' if ok else 'not met'}**")
    if "rlb-udp-1" in by and "udp" in by:
        x = ratio(by["rlb-udp-1"].rate, by["udp"].rate)
        lines.append(f"- rlbridge UDP, 1 value/datagram: {fmt(x, 2)} x the raw UDP loop; "
                     f"target >= 0.40: **{'met' if x >= 0.4 else 'not met'}**")
    return lines


def flow_targets(results: Sequence[CaseResult]) -> list[str]:
    """Flow control: the slow reader's rows lose nothing and the writer keeps its pace."""
    lines = []
    for r in results:
        if not (r.case.sub_rate and r.runs):
            continue
        lost = sum(m.loss.get("end to end", 0) for m in r.runs)
        pace = median([ratio(m.pub_rate, m.rate) for m in r.runs])
        ok = lost == 0 and pace <= 1.1
        verdict = ("target (nothing lost, written/s within 10 % of read/s): "
                   f"**{'met' if ok else 'not met'}**" if r.case.flow
                   else "(no flow control: the comparison)")
        lines.append(f"- {r.case.label}: {lost:,} values lost over {len(r.runs)} runs; the "
                     f"publisher wrote {fmt(pace, 2)} x the reader's rate; {verdict}")
    return lines


def report(results: Sequence[CaseResult], settings: Settings, command: Sequence[str]) -> str:
    """The markdown section ``rlbridge bench throughput --out`` writes."""
    flood = "as fast as flow control allows" if not settings.rate else \
        f"offered at {settings.rate:,.0f} values/s"
    parts = [
        report_header("Throughput", command),
        f"{settings.repeats} repeats per row, interleaved; each run sends up to "
        f"{settings.count:,} values or for {settings.seconds:g} s ({flood}). Figures are "
        "medians over the repeats. values/s = values the receiving process read, divided by "
        "the time from the sender's first send to that receiver's last arrival. CPU = user + "
        "system seconds of each whole process (all threads, /proc/<pid>/stat) over the run, "
        "per million values received. rlbridge rows: 3 processes, 2 hops (publisher -> "
        "server -> subscriber); baselines: 2 processes, 1 hop, 8-byte messages.",
        "",
        table(results),
        "",
        "Targets:",
        "",
        *targets(results),
        *flow_targets(results),
        "",
        "Losses of the rlbridge rows by stage. Each stage is what entered it minus what "
        "entered the next (publisher ring: written - taken by the send thread; hop 1: taken - "
        "accepted by the server; server: accepted - sent to the subscriber; hop 2: sent - "
        "arrived in the subscriber's ring; subscriber ring: arrived - read), so the stages add "
        "up to the end-to-end loss. The last column counts some of the same loss another way "
        "(sequence gaps at each receiver, values the server dropped for a full send "
        "buffer or backlog; session restarts, after which the server's counters start again "
        "and the stages are not known). "
        "`written/s` is the publisher's rate over the second half of its writing (the path "
        "full; the whole run when it finished early), `read/s` the subscriber's: with flow "
        "control the first follows the second.",
        "",
        loss_table(results),
    ]
    return "\n".join(parts) + "\n"
