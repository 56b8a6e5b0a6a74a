"""One cycle of the pan-tilt loop controller (the ``Loop`` and ``Safety/IO`` of thesis fig. 3.2).

:meth:`PanTiltLoop.cycle` is the whole hard-real-time body: sample the encoders, decide the
state, compute both axes, write the PWM duties. It takes the time and the set-point inputs as
arguments and touches no channel, socket or clock, so the CSP process around it
(:mod:`rlbridge.demo.controller`) stays a thin adapter and tests can run it on a fake clock.

States (sent to the middleware as the status string when they change)::

    idle ──first fresh set-points──▶ tracking ──set-point older than stale_after──▶ safe
                                        ▲                                           │
                                        └──────────────fresh set-points─────────────┘
    any state ──bridge link lost──▶ lost-link ──link back (the SDK reconnected)──▶ safe/tracking

In every state but ``tracking`` the camera holds position: the reference is brought (at the
follower's rate limit) to the angle measured when the state was entered, and stays there. That
is the safe behaviour for a camera whose set-point stream stopped, whatever the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rlbridge._compat import StrEnum
from rlbridge.demo.control import AxisController, Gains, SetpointFollower
from rlbridge.demo.plant import RAD_PER_COUNT, PanTiltPlant


class ControllerState(StrEnum):
    """The status the controller reports over TCP when it changes."""

    IDLE = "idle"
    TRACKING = "tracking"
    SAFE = "safe"
    LOST_LINK = "lost-link"


@dataclass(frozen=True, slots=True)
class LoopConfig:
    """Tuning of the loop; the defaults suit the simulated plant and a 30 Hz vision node."""

    stale_after: float = 0.15
    """Set-points older than this (s, about 4 frames at 30 Hz) put the loop in ``safe``."""
    max_speed: float = 3.0
    """Rate limit of the reference (rad/s), well under the motors' ~15 rad/s."""
    pan_limits: tuple[float, float] = (-2.5, 2.5)
    tilt_limits: tuple[float, float] = (-1.2, 1.2)
    settle: float = 0.3
    """Seconds after entering ``tracking`` that are left out of the error statistics."""
    bandwidth_hz: float = 8.0


@dataclass(frozen=True, slots=True)
class SetpointSample:
    """What the loop learned from one set-point channel this cycle."""

    value: float
    stamp_ns: int
    """Identity of the newest value (changes when a new one arrives); 0 before the first."""
    age_ns: int
    """How long ago the newest value was sent (-1 before the first)."""


NO_SETPOINT = SetpointSample(0.0, 0, -1)


class ErrorStats:
    """Running RMS and maximum of one axis's tracking error (reference minus measured angle)."""

    __slots__ = ("count", "max_abs", "sum_sq")

    def __init__(self) -> None:
        self.count = 0
        self.sum_sq = 0.0
        self.max_abs = 0.0

    def add(self, error: float) -> None:
        self.count += 1
        self.sum_sq += error * error
        self.max_abs = max(self.max_abs, abs(error))

    @property
    def rms(self) -> float:
        return math.sqrt(self.sum_sq / self.count) if self.count else math.nan


class _AxisLoop:
    __slots__ = ("angle", "controller", "follower", "last_stamp", "stats")

    def __init__(self, gains: Gains, max_speed: float, limits: tuple[float, float]) -> None:
        self.follower = SetpointFollower(max_speed=max_speed, limits=limits)
        self.controller = AxisController(gains)
        self.stats = ErrorStats()
        self.last_stamp = 0
        self.angle = 0.0

    def take(self, sp: SetpointSample, now_ns: int) -> None:
        if sp.stamp_ns and sp.stamp_ns != self.last_stamp:
            self.last_stamp = sp.stamp_ns
            age = min(max(sp.age_ns, 0), 100_000_000)  # clocks of two hosts may disagree
            self.follower.on_setpoint(sp.value, now_ns - age)


class PanTiltLoop:
    """The loop body; see the module docstring. Not thread-safe: one HRT thread calls it."""

    def __init__(self, plant: PanTiltPlant, config: LoopConfig | None = None) -> None:
        cfg = config or LoopConfig()
        self.config = cfg
        self.plant = plant
        self.pan = _AxisLoop(Gains.for_axis(plant.pan.params, cfg.bandwidth_hz), cfg.max_speed,
                             cfg.pan_limits)
        self.tilt = _AxisLoop(Gains.for_axis(plant.tilt.params, cfg.bandwidth_hz),
                              cfg.max_speed, cfg.tilt_limits)
        self.state = ControllerState.IDLE
        self._stale_ns = round(cfg.stale_after * 1e9)
        self._settle_ns = round(cfg.settle * 1e9)
        self._tracking_since = 0
        self._last_ns: int | None = None

    def cycle(self, now_ns: int, pan_sp: SetpointSample, tilt_sp: SetpointSample,
              link_lost: bool) -> ControllerState | None:
        """Run one control cycle at ``now_ns``; return the new state if it changed."""
        pan_counts, tilt_counts = self.plant.sample(now_ns)
        pan, tilt = self.pan, self.tilt
        pan.angle = (pan_counts + 0.5) * RAD_PER_COUNT  # centre of the count: no bias
        tilt.angle = (tilt_counts + 0.5) * RAD_PER_COUNT
        last = self._last_ns
        self._last_ns = now_ns
        if last is None:
            for axis in (pan, tilt):
                axis.follower.reset(axis.angle)
                axis.controller.reset(axis.angle)
            dt = 0.001
        else:
            dt = min(max((now_ns - last) * 1e-9, 1e-4), 0.05)
        pan.take(pan_sp, now_ns)
        tilt.take(tilt_sp, now_ns)
        changed = self._decide(now_ns, pan_sp, tilt_sp, link_lost)
        tracking_settled = (self.state is ControllerState.TRACKING
                            and now_ns - self._tracking_since >= self._settle_ns)
        duties = []
        for axis in (pan, tilt):
            reference = axis.follower.update(now_ns, dt)
            duties.append(axis.controller.update(reference, axis.follower.speed, axis.angle, dt))
            if tracking_settled:
                axis.stats.add(reference - axis.angle)
        self.plant.actuate(duties[0], duties[1])
        return changed

    def _decide(self, now_ns: int, pan_sp: SetpointSample, tilt_sp: SetpointSample,
                link_lost: bool) -> ControllerState | None:
        if link_lost:
            new = ControllerState.LOST_LINK
        elif pan_sp.age_ns < 0 or tilt_sp.age_ns < 0:
            new = self.state  # until both axes have a set-point, stay where we are (idle)
        elif max(pan_sp.age_ns, tilt_sp.age_ns) > self._stale_ns:
            new = ControllerState.SAFE
        else:
            new = ControllerState.TRACKING
        if new is self.state:
            return None
        self.state = new
        for axis in (self.pan, self.tilt):
            if new is ControllerState.TRACKING:
                axis.follower.follow()
            else:
                axis.follower.hold(axis.angle)
        if new is ControllerState.TRACKING:
            self._tracking_since = now_ns
        return new
