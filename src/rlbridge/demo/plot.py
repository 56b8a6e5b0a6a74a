"""The end-of-run PNG: set-point against angle per axis, tracking error, and the path.

matplotlib is imported here, lazily, with the non-interactive Agg backend selected on the figure
itself (no ``matplotlib.use``, no pyplot state machine), so writing a plot needs no display and
changes nothing global. matplotlib is an optional dependency (``pip install -e '.[plot]'`` in a
checkout); without it :func:`write_plot` raises :class:`PlotUnavailable` with that advice.
"""

from __future__ import annotations

import bisect
import itertools
import math
from pathlib import Path
from typing import Any

from rlbridge._version import pip_install
from rlbridge.demo.metrics import MAX_FRAME_GAP, TrackingMetrics, errors
from rlbridge.demo.monitor import GONE, TraceSnapshot
from rlbridge.demo.topics import AXES, Diagnostics

DEFAULT_NAME = "pan_tilt.png"

_SHADE = {"idle": ("#bdbdbd", "idle"), "safe": ("#ffcc80", "safe (hold)"),
          "lost-link": ("#ef9a9a", "lost-link (hold)"),
          GONE: ("#e0e0e0", "no controller session")}


class PlotUnavailable(RuntimeError):
    """matplotlib is not installed."""


def resolve_path(path: str | Path) -> Path:
    """Where ``--plot PATH`` writes: a directory gets ``pan_tilt.png`` inside.

    A directory is one that exists, a name written with a trailing slash (``out/``: give the
    string as typed, ``Path`` drops the slash), or a name without an extension (``out``);
    :func:`write_plot` creates it. Anything else is the file itself.
    """
    text = str(path)
    target = Path(text)
    if target.is_dir() or text.endswith(("/", "\\")) or not target.suffix:
        return target / DEFAULT_NAME
    return target


def write_plot(snap: TraceSnapshot, metrics: TrackingMetrics, path: Path,
               diag: Diagnostics | None = None, title: str = "rlbridge pan-tilt demo") -> Path:
    """Write the figure to ``path`` (a directory gets ``pan_tilt.png``); return the file."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Patch
    except ImportError as exc:
        raise PlotUnavailable(
            f"the plot needs matplotlib ({exc}): {pip_install('plot')}") from None
    target = resolve_path(path)
    target.parent.mkdir(parents=True, exist_ok=True)

    fig = Figure(figsize=(13, 7.5), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 2, width_ratios=(2.3, 1))
    ax_pan = fig.add_subplot(grid[0, 0])
    ax_tilt = fig.add_subplot(grid[1, 0], sharex=ax_pan)
    ax_err = fig.add_subplot(grid[2, 0], sharex=ax_pan)
    _axis_panel(ax_pan, snap, "pan")
    _axis_panel(ax_tilt, snap, "tilt")
    ax_pan.legend(loc="upper right", fontsize=8, ncols=2)
    _error_panel(ax_err, snap, metrics)
    handles, _ = ax_err.get_legend_handles_labels()
    handles += [Patch(color=c, alpha=0.5, label=label) for c, label in _SHADE.values()]
    handles.append(Patch(facecolor="none", edgecolor="#9e9e9e", hatch="///",
                         label="no set-points (target not seen)"))
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=8)
    ax_pan.set_xlim(0, max(snap.elapsed, 0.1))
    _path_panel(fig.add_subplot(grid[:, 1]), snap)
    fig.suptitle(_headline(title, metrics, diag), fontsize=11)
    fig.savefig(target, dpi=110)
    return target


def _axis_panel(axes: Any, snap: TraceSnapshot, axis: str) -> None:
    """Set-point steps (as published) and the angle (as received) of one axis."""
    index = 1 if axis == "pan" else 2
    angles = snap.angles.get(axis, [])
    axes.step([s[0] for s in snap.setpoints], [s[index] for s in snap.setpoints], where="post",
              color="#f57c00", lw=1.2, label="set-point (vision, 30 Hz, UDP)")
    axes.plot([a[0] for a in angles], [a[1] for a in angles], color="#1565c0", lw=1.4,
              label="angle (controller, 50 Hz, UDP)")
    axes.set_ylabel(f"{axis} [rad]")
    _shade(axes, snap.statuses, snap.elapsed)
    _hatch_gaps(axes, snap)
    axes.grid(alpha=0.3)
    axes.tick_params(labelbottom=False)


def _error_panel(axes: Any, snap: TraceSnapshot, metrics: TrackingMetrics) -> None:
    colours = {"pan": "#1565c0", "tilt": "#2e7d32"}
    for axis in AXES:
        errs = _with_breaks(errors(snap, axis))
        m = metrics.axis(axis)
        label = (f"{axis}: rms {m.rms * 1e3:.1f} mrad, max {m.max_abs * 1e3:.1f} mrad"
                 if m.samples else f"{axis}: no settled tracking samples")
        axes.plot([e[0] for e in errs], [e[1] * 1e3 for e in errs], color=colours[axis],
                  lw=1.0, label=label)
    axes.set_ylabel("set-point - angle [mrad]")
    axes.set_xlabel("time [s] (middleware clock)")
    _shade(axes, snap.statuses, snap.elapsed)
    _hatch_gaps(axes, snap)
    axes.grid(alpha=0.3)
    _limit_error_axis(axes, snap)


def _path_panel(axes: Any, snap: TraceSnapshot) -> None:
    """Pan against tilt: the Lissajous figure the camera drew."""
    axes.plot([s[1] for s in snap.setpoints], [s[2] for s in snap.setpoints], ".",
              color="#f57c00", ms=3, label="set-points")
    pan = snap.angles.get("pan", [])
    tilt = snap.angles.get("tilt", [])
    n = min(len(pan), len(tilt))
    axes.plot([p[1] for p in pan[:n]], [t[1] for t in tilt[:n]], color="#1565c0", lw=1.0,
              label="camera angle")
    axes.set_xlabel("pan [rad]")
    axes.set_ylabel("tilt [rad]")
    axes.set_title("where the camera pointed", fontsize=10)
    axes.grid(alpha=0.3)
    axes.legend(loc="upper right", fontsize=8)


def _with_breaks(samples: list[tuple[float, float]], gap: float = 0.1
                 ) -> list[tuple[float, float]]:
    """Insert a NaN where samples are ``gap`` apart, so the line is broken, not bridged."""
    out: list[tuple[float, float]] = []
    for sample in samples:
        if out and sample[0] - out[-1][0] > gap:
            out.append((out[-1][0], math.nan))
        out.append(sample)
    return out


def _headline(title: str, metrics: TrackingMetrics, diag: Diagnostics | None) -> str:
    parts = [title]
    if metrics.samples:
        parts.append(f"tracking error rms pan {metrics.pan.rms * 1e3:.1f} / "
                     f"tilt {metrics.tilt.rms * 1e3:.1f} mrad")
    if diag is not None:
        parts.append(f"1 kHz loop lateness p99 {diag.late_p99_us / 1e3:.2f} ms")
        parts.append(f"set-points lost {diag.setpoints_lost}")
    return " · ".join(parts)


def _shade(axes: Any, statuses: list[tuple[float, str]], end: float) -> None:
    """Shade the intervals the controller spent holding position (any state but tracking)."""
    for i, (start, state) in enumerate(statuses):
        stop = statuses[i + 1][0] if i + 1 < len(statuses) else end
        if state in _SHADE and stop > start:
            axes.axvspan(start, stop, color=_SHADE[state][0], alpha=0.5, lw=0)


def _hatch_gaps(axes: Any, snap: TraceSnapshot) -> None:
    """Hatch where the vision node published nothing for longer than a frame gap."""
    times = [s[0] for s in snap.setpoints]
    for before, after in itertools.pairwise(times):
        if after - before > MAX_FRAME_GAP:
            axes.axvspan(before, after, facecolor="none", edgecolor="#9e9e9e", hatch="///",
                         lw=0)


def _limit_error_axis(axes: Any, snap: TraceSnapshot) -> None:
    """Scale to the tracking error, not to the swing after a dropout (which is clipped)."""
    settled = []
    times = [s[0] for s in snap.statuses]
    for axis in AXES:
        for t, err in errors(snap, axis):
            i = bisect.bisect_right(times, t) - 1
            if i >= 0 and snap.statuses[i][1] == "tracking" and t - times[i] > 0.5:
                settled.append(abs(err) * 1e3)
    if settled:
        top = max(5.0, 3.0 * sorted(settled)[int(0.99 * (len(settled) - 1))])
        axes.set_ylim(-top, top)

