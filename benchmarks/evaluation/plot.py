"""The evaluation's figures, in the thesis's style: latency (ms) per sample, one line per row.

Lost samples are drawn as markers on the x axis (the thesis's figure 4.3 counts them beside
the plot); every figure is a PNG under the directory given, named by its scenario group.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from benchmarks.evaluation.sweep import Evaluation, Row, ThroughputPoint

COLORS = {"tcp": "tab:red", "tcpn": "tab:orange", "udp": "tab:blue", "zmq": "tab:green",
          "zenoh": "tab:purple", "tcpn-latest": "tab:brown", "udp-k1": "tab:cyan",
          "udp-k2": "tab:olive", "tcp-maxage": "tab:pink", "udp-maxage": "tab:gray",
          "tcp-maxage-drop": "tab:brown"}


def _plot_rows(ax: object, rows: Sequence[Row], title: str) -> None:
    from matplotlib.axes import Axes

    assert isinstance(ax, Axes)
    for row in rows:
        if row.summary is None:
            continue
        xs = [i for i, v in enumerate(row.latencies_ms) if v is not None]
        ys = [v for v in row.latencies_ms if v is not None]
        color = COLORS.get(row.key)
        ax.plot(xs, ys, lw=0.8, color=color, label=f"{row.label} (lost {row.summary.lost})")
        lost = [i for i, v in enumerate(row.latencies_ms) if v is None]
        if lost:
            ax.plot(lost, [0.0] * len(lost), "x", color=color, ms=5)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("sample (100 Hz)")
    ax.set_ylabel("latency (ms)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")


def _figure(groups: Sequence[tuple[str, Sequence[Row]]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(groups), 1, figsize=(9, 3.0 * len(groups)), squeeze=False)
    for ax, (title, rows) in zip(axes[:, 0], groups, strict=True):
        _plot_rows(ax, rows, title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _throughput_figure(points: Sequence[ThroughputPoint], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for direction in ("up", "down"):
        for transport in ("udp", "tcp"):
            pts = [p for p in points if p.direction == direction and p.transport == transport]
            if pts:
                ax.plot([p.offered_hz for p in pts], [p.received_per_s for p in pts], "o-",
                        label=f"{direction} {transport}")
    top = max((p.offered_hz for p in points), default=1)
    ax.plot([100, top], [100, top], "k:", lw=0.8, label="offered")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("sender frequency (Hz)")
    ax.set_ylabel("values/s received")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def figures(ev: Evaluation, titles: dict[str, str], out_dir: Path) -> dict[str, Path]:
    """Write every figure; returns group name -> PNG path."""
    out_dir.mkdir(parents=True, exist_ok=True)

    def rows(scenario: str, kinds: tuple[str, ...]) -> list[Row]:
        return [r for r in ev.rows if r.scenario == scenario and r.kind in kinds]

    made: dict[str, Path] = {}
    plans: dict[str, list[tuple[str, list[Row]]]] = {
        "reference": [("reference", rows("reference", ("rlbridge",)))],
        "delay": [(s, rows(s, ("rlbridge",))) for s in ("delay3", "delay7.5", "delay15")],
        "loss": [("loss1", rows("loss1", ("rlbridge",)))],
        "srt": [(s, rows(s, ("rlbridge",))) for s in ("srt100", "up-reference")],
        "baselines": [(s, [r for r in rows(s, ("rlbridge", "baseline")) if r.key != "tcp"])
                      for s in ("delay7.5", "loss1")],
        "policies": [(s, rows(s, ("policy",)) + [r for r in rows(s, ("rlbridge",))
                                                 if r.key == "udp"])
                     for s in ("delay7.5", "loss1")],
    }
    for name, groups in plans.items():
        kept = [(titles.get(s, s), rs) for s, rs in groups
                if any(r.summary is not None for r in rs)]
        if kept:
            made[name] = _figure(kept, out_dir / f"{name}.png")
    if ev.throughput:
        made["throughput"] = _throughput_figure(ev.throughput, out_dir / "throughput.png")
    return made
