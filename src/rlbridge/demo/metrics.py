"""Tracking error as the middleware sees it: published set-points against returned angles.

The reference at time ``t`` is the set-point stream interpolated linearly between frames (the
path the vision node asked for). Where the stream has a gap longer than :data:`MAX_FRAME_GAP`
(the target was lost) there is no reference and no error, and none after the newest frame
either (holding it would charge the controller for the frame not yet taken). Each angle
received at ``t`` is compared with the reference at ``t``. The angle was measured about a loop
period plus the network latency earlier, so the error includes that delay (and any stall of
either process on a loaded machine): it is what a user comparing the two topics would see. The
median is given next to RMS and maximum because it shrugs off such stalls.

Only samples taken while the controller reported ``tracking`` count, minus ``settle`` seconds
after each entry into ``tracking`` (the camera first has to swing to the target).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from rlbridge.demo.monitor import TraceSnapshot
from rlbridge.demo.topics import AXES

MAX_FRAME_GAP = 0.1
"""Seconds between two set-points beyond which the stream is not interpolated."""

TRACKING = "tracking"


@dataclass(frozen=True, slots=True)
class AxisMetrics:
    samples: int
    rms: float
    """Root mean square error in rad (NaN without samples)."""
    max_abs: float
    median_abs: float

    def as_dict(self) -> dict[str, float | int]:
        return {"samples": self.samples, "rms_mrad": self.rms * 1e3,
                "max_mrad": self.max_abs * 1e3, "median_mrad": self.median_abs * 1e3}


@dataclass(frozen=True, slots=True)
class TrackingMetrics:
    pan: AxisMetrics
    tilt: AxisMetrics
    settle: float

    def axis(self, name: str) -> AxisMetrics:
        return self.pan if name == "pan" else self.tilt

    @property
    def worst_rms(self) -> float:
        """The larger RMS error of the two axes (NaN when an axis has no samples)."""
        return max(self.pan.rms, self.tilt.rms) if self.samples else math.nan

    @property
    def samples(self) -> int:
        return min(self.pan.samples, self.tilt.samples)


class Reference:
    """The set-point stream of one axis as a function of time (see the module docstring)."""

    def __init__(self, setpoints: list[tuple[float, float, float]], axis: str) -> None:
        index = 1 if axis == "pan" else 2
        self._t = [s[0] for s in setpoints]
        self._v = [s[index] for s in setpoints]

    def at(self, t: float) -> float | None:
        """The reference at ``t``, or ``None`` where the stream says nothing (see above)."""
        i = bisect.bisect_right(self._t, t) - 1
        if i < 0:
            return None
        if i + 1 >= len(self._t):
            return None
        t0, t1 = self._t[i], self._t[i + 1]
        if t1 - t0 > MAX_FRAME_GAP:
            return None
        return self._v[i] + (self._v[i + 1] - self._v[i]) * (t - t0) / (t1 - t0)


def state_at(statuses: list[tuple[float, str]], t: float) -> tuple[str, float]:
    """The controller's reported state at ``t`` and when it was entered (``("", 0)`` before any)."""
    i = bisect.bisect_right([s[0] for s in statuses], t) - 1
    return ("", 0.0) if i < 0 else (statuses[i][1], statuses[i][0])


def errors(snap: TraceSnapshot, axis: str) -> list[tuple[float, float]]:
    """``(t, reference - angle)`` for every received angle that has a reference."""
    ref = Reference(snap.setpoints, axis)
    out = []
    for t, angle in snap.angles.get(axis, []):
        r = ref.at(t)
        if r is not None:
            out.append((t, r - angle))
    return out


def tracking_metrics(snap: TraceSnapshot, settle: float = 0.5) -> TrackingMetrics:
    """RMS and maximum error per axis over the settled ``tracking`` intervals."""
    times = [s[0] for s in snap.statuses]
    per_axis = []
    for axis in AXES:
        settled = []
        for t, err in errors(snap, axis):
            i = bisect.bisect_right(times, t) - 1
            if i >= 0 and snap.statuses[i][1] == TRACKING and t - times[i] >= settle:
                settled.append(abs(err))
        if not settled:
            per_axis.append(AxisMetrics(0, math.nan, math.nan, math.nan))
            continue
        settled.sort()
        rms = math.sqrt(sum(e * e for e in settled) / len(settled))
        per_axis.append(AxisMetrics(len(settled), rms, settled[-1], settled[len(settled) // 2]))
    return TrackingMetrics(per_axis[0], per_axis[1], settle)
