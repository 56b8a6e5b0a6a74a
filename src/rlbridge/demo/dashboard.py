"""Live view of the demo in a terminal: plain ANSI escapes, no dependency.

Two views of the same :class:`Status` (built from a trace snapshot, i.e. from what the
middleware side received):

* :class:`AnsiDashboard` redraws a dozen lines in place, ten times a second: set-point against
  angle per axis (numbers and a bar), tracking error, loop lateness, link state and values
  lost. Used when stdout is a terminal.
* :class:`LineReport` prints one line a second, for logs, pipes, CI and ``--no-dashboard``.

Both only format; they never block the demo (a write to a slow terminal is the main thread's
problem, the loop controller runs in its own threads).
"""

from __future__ import annotations

import math
import re
import shutil
from dataclasses import dataclass
from typing import Protocol, TextIO

from rlbridge.demo.metrics import Reference, TrackingMetrics, tracking_metrics
from rlbridge.demo.monitor import GONE, TraceSnapshot
from rlbridge.demo.topics import AXES, Diagnostics

WINDOW = 5.0
"""Seconds of history the live error statistics cover."""


@dataclass(frozen=True)
class Status:
    """Everything a view shows, derived from one snapshot."""

    title: str
    elapsed: float
    duration: float
    snapshot: TraceSnapshot
    metrics: TrackingMetrics

    @classmethod
    def of(cls, title: str, snap: TraceSnapshot, duration: float) -> Status:
        return cls(title, snap.elapsed, duration, snap, tracking_metrics(snap, settle=0.5))

    @property
    def diag(self) -> Diagnostics | None:
        return self.snapshot.diagnostics

    @property
    def state(self) -> str:
        statuses = self.snapshot.statuses
        return statuses[-1][1] if statuses else "(no controller yet)"

    @property
    def link(self) -> str:
        """The controller's link as its last diagnostics said, unless its session has closed
        since (then those diagnostics describe a controller that is gone)."""
        if self.state == GONE:
            return "closed"
        return self.diag.link if self.diag is not None else "-"

    def axis_now(self, axis: str) -> tuple[float, float, float]:
        """Latest set-point, latest angle, and the newest error that is known; NaN if none.

        The error needs the frame after the angle (see :mod:`rlbridge.demo.metrics`), so it
        is the one of an angle some tens of milliseconds old.
        """
        snap = self.snapshot
        index = 1 if axis == "pan" else 2
        sp = snap.setpoints[-1][index] if snap.setpoints else math.nan
        angles = snap.angles.get(axis, [])
        angle = angles[-1][1] if angles else math.nan
        ref = Reference(snap.setpoints, axis)
        for t, value in reversed(angles[-10:]):
            r = ref.at(t)
            if r is not None:
                return sp, angle, r - value
        return sp, angle, math.nan

    def angles_lost(self) -> int:
        """Angles sent to this bridge that never arrived (live: may count one in flight)."""
        return self.snapshot.angles_lost


class View(Protocol):
    def update(self, status: Status) -> None: ...
    def close(self) -> None: ...


def _mrad(value: float) -> str:
    return "-" if math.isnan(value) else f"{value * 1e3:+.1f}"


def _rad(value: float) -> str:
    return "   -  " if math.isnan(value) else f"{value:+.3f}"


def _ms(us: float) -> str:
    return f"{us / 1e3:.2f} ms"


def _bar(setpoint: float, angle: float, width: int = 33, span: float = 1.0) -> str:
    """``[....|....o....]``: '|' the set-point, 'o' the angle, 'O' both; range +-span rad."""
    cells = ["."] * width
    cells[width // 2] = ":"

    def cell(value: float) -> int | None:
        if math.isnan(value):
            return None
        return round((max(-span, min(span, value)) + span) / (2 * span) * (width - 1))

    sp, an = cell(setpoint), cell(angle)
    if sp is not None:
        cells[sp] = "|"
    if an is not None:
        cells[an] = "O" if an == sp else "o"
    return "[" + "".join(cells) + "]"


_ESCAPE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _clip(line: str, width: int) -> str:
    """Cut ``line`` to ``width`` visible characters (escape codes do not count): a wrapped line
    would break the cursor arithmetic of the redraw."""
    if len(_ESCAPE.sub("", line)) <= width:
        return line
    out, visible, i = [], 0, 0
    while i < len(line) and visible < width:
        match = _ESCAPE.match(line, i)
        if match:
            out.append(match.group())
            i = match.end()
            continue
        out.append(line[i])
        visible += 1
        i += 1
    return "".join(out) + "\x1b[0m"


_COLOURS = {"tracking": "32", "idle": "33", "safe": "33", "lost-link": "31", GONE: "31"}


class AnsiDashboard:
    """Redraws in place with cursor movement; see the module docstring."""

    def __init__(self, stream: TextIO) -> None:
        self._out = stream
        self._lines = 0

    def _colour(self, text: str, state: str) -> str:
        code = _COLOURS.get(state, "0")
        return f"\x1b[{code};1m{text}\x1b[0m"

    def render(self, status: Status) -> list[str]:
        diag = status.diag
        snap = status.snapshot
        total = f" / {status.duration:.1f} s" if status.duration > 0 else " s"
        link = status.link
        age = (f"{diag.setpoint_age_ms:.0f} ms" if diag is not None and status.state != GONE
               else "-")
        lines = [
            f"\x1b[1m{status.title}\x1b[0m | {status.elapsed:5.1f}{total}",
            f" controller  {self._colour(status.state.upper(), status.state)}"
            f"   link {link}   set-point age {age}",
        ]
        if diag is None:
            lines += [" loop        no diagnostics from the controller yet", ""]
        else:
            lines += [
                f" loop        1 kHz, lateness p50 {_ms(diag.late_p50_us)}, "
                f"p99 {_ms(diag.late_p99_us)}, max {_ms(diag.late_max_us)}",
                f"             missed {diag.missed} of {diag.cycles} cycles, {diag.scheduling}",
            ]
        lines += [
            f" lost        set-points {diag.setpoints_lost if diag else 0} of "
            f"{diag.setpoints_received + diag.setpoints_lost if diag else 0} (UDP), "
            f"angles {status.angles_lost()} of "
            f"{snap.angles_sent} (UDP)",
            "",
            " axis  set-point   angle  error mrad  -1 rad          0          +1 rad",
        ]
        for axis in AXES:
            sp, angle, err = status.axis_now(axis)
            lines.append(f" {axis:<5} {_rad(sp):>8}  {_rad(angle):>7}   {_mrad(err):>7}    "
                         f"{_bar(sp, angle)}")
        m = status.metrics
        parts = [f"{axis} rms {a.rms * 1e3:.1f} max {a.max_abs * 1e3:.1f}" if a.samples
                 else f"{axis} -" for axis, a in (("pan", m.pan), ("tilt", m.tilt))]
        lines.append(f" error mrad  last {WINDOW:.0f} s: " + " | ".join(parts))
        lines.append(" states      " + states_line(snap.statuses, limit=4))
        return [_clip(line, self._width()) for line in lines]

    def _width(self) -> int:
        return max(40, shutil.get_terminal_size((100, 24)).columns - 1)

    def update(self, status: Status) -> None:
        lines = self.render(status)
        out = self._out
        if self._lines:
            out.write(f"\x1b[{self._lines}F")
        else:
            out.write("\x1b[?25l")  # hide the cursor while redrawing
        for line in lines:
            out.write("\x1b[2K" + line + "\n")
        self._lines = len(lines)
        out.flush()

    def close(self) -> None:
        if self._lines:
            self._out.write("\x1b[?25h")
            self._out.flush()


class LineReport:
    """One line per ``every`` seconds; see the module docstring."""

    def __init__(self, stream: TextIO, every: float = 1.0) -> None:
        self._out = stream
        self._every = every
        self._next = 0.0

    def update(self, status: Status) -> None:
        if status.elapsed < self._next:
            return
        self._next = status.elapsed + self._every
        diag = status.diag
        axes = []
        for axis in AXES:
            sp, angle, err = status.axis_now(axis)
            axes.append(f"{axis} sp {_rad(sp)} angle {_rad(angle)} err {_mrad(err).strip()} mrad")
        lateness = (f"p99 {_ms(diag.late_p99_us)} missed {diag.missed}" if diag is not None
                    else "p99 -")
        lost = diag.setpoints_lost if diag is not None else 0
        self._out.write(
            f"t={status.elapsed:5.1f}s {status.state:<10} link {status.link:<9} "
            f"{' | '.join(axes)} | loop {lateness} | lost sp {lost} angles "
            f"{status.angles_lost()}\n")
        self._out.flush()

    def close(self) -> None:
        pass


def states_line(statuses: list[tuple[float, str]], limit: int = 6) -> str:
    """``idle 0.0 s -> tracking 0.5 s -> ...`` (the last ``limit`` changes)."""
    if not statuses:
        return "-"
    shown = statuses[-limit:]
    prefix = "... -> " if len(statuses) > limit else ""
    return prefix + " -> ".join(f"{state} {t:.2f} s" for t, state in shown)
