"""The per-axis control law of the pan-tilt loop: pure arithmetic, time passed in.

Two pieces per axis, both free of I/O and clocks so that tests run them against the simulated
plant on a fake clock:

* :class:`SetpointFollower` turns set-points that arrive at the camera's frame rate (30 Hz,
  with network jitter and the odd lost datagram) into a reference for a 1 kHz loop. Stepping the
  loop's reference 30 times a second would make the camera jerk and lag half a frame behind; so
  the follower estimates the target's speed from consecutive set-points and extrapolates between
  frames (first-order hold), for at most ``max_extrapolation`` so that a stream that stops does
  not run the camera away. A rate limiter (``max_speed``) bounds every reference jump, which is
  what makes re-acquiring a target after a dropout, or holding after a fault, smooth.
* :class:`AxisController` is a PID with velocity feed-forward: proportional and integral action
  on the position error, derivative action on the *speed* error (reference speed minus the
  filtered encoder speed, so that reference jumps do not kick the output), and the feed-forward
  ``kff * v_ref`` that supplies the duty a constant speed needs, leaving the feedback terms only
  the residual error. The integrator is clamped and frozen while the output saturates in the
  direction of the error (anti-windup).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rlbridge.demo.plant import RAD_PER_COUNT, AxisParams


@dataclass(frozen=True, slots=True)
class Gains:
    """Controller gains of one axis, in duty (-1..1) per radian, per rad/s and per rad s."""

    kp: float
    ki: float
    kd: float
    kff: float
    speed_filter: float = 0.003
    """Time constant (s) of the low-pass on the encoder speed; one count per cycle is 1.5 rad/s."""
    integral_limit: float = 0.3
    """Largest duty the integral term may contribute."""

    @classmethod
    def for_axis(cls, params: AxisParams, bandwidth_hz: float = 8.0,
                 damping_ratio: float = 0.8) -> Gains:
        """Pole placement on the motor model ``G(s) = k / (s (s + a))``.

        With ``u = kp e + kd (v_ref - w)`` the closed loop is ``s^2 + (a + k kd) s + k kp``;
        matching ``s^2 + 2 zeta wn s + wn^2`` gives the gains. The integral gain puts its zero
        a decade below ``wn``; ``kff`` is the inverse of the steady-state speed per duty.
        """
        k = params.torque_per_duty / params.inertia
        a = params.damping / params.inertia
        wn = 2.0 * math.pi * bandwidth_hz
        kp = wn * wn / k
        kd = max(0.0, (2.0 * damping_ratio * wn - a) / k)
        return cls(kp=kp, ki=kp * wn / 10.0, kd=kd, kff=1.0 / params.max_speed)


class SetpointFollower:
    """Frame-rate set-points in, a smooth rate-limited reference out; see the module docstring."""

    __slots__ = ("_following", "_have_sp", "_hold", "_last_at", "_limits", "_max_extra",
                 "_max_speed", "_smoothing", "_sp", "_sp_at", "_v_est", "reference", "speed")

    def __init__(self, *, max_speed: float, limits: tuple[float, float],
                 max_extrapolation: float = 0.05, smoothing: float = 0.6) -> None:
        if max_speed <= 0:
            raise ValueError(f"max_speed must be positive, got {max_speed}")
        if not limits[0] < limits[1]:
            raise ValueError(f"limits must be (low, high) with low < high, got {limits}")
        self._max_speed = max_speed
        self._limits = limits
        self._max_extra = round(max_extrapolation * 1e9)
        self._smoothing = smoothing
        self._following = False
        self._have_sp = False
        self._hold = 0.0
        self._sp = 0.0
        self._sp_at = 0
        self._last_at = 0
        self._v_est = 0.0
        #: The reference angle (rad) and its speed (rad/s) after the last :meth:`update`.
        self.reference = 0.0
        self.speed = 0.0

    def reset(self, angle: float) -> None:
        """Start at ``angle``, holding it (no set-point known)."""
        self.reference = angle
        self.speed = 0.0
        self.hold(angle)
        self._have_sp = False

    def hold(self, angle: float) -> None:
        """Stop following: the reference moves (rate-limited) to ``angle`` and stays there."""
        self._following = False
        self._hold = angle
        self._v_est = 0.0

    def follow(self) -> None:
        """Follow the set-points again, starting from where the reference is now."""
        self._following = True

    def on_setpoint(self, value: float, at_ns: int) -> None:
        """A new set-point that described the target at monotonic time ``at_ns``."""
        if self._have_sp and 0 < at_ns - self._sp_at < 200_000_000:
            measured = (value - self._sp) / ((at_ns - self._sp_at) * 1e-9)
            v = self._v_est + self._smoothing * (measured - self._v_est)
            self._v_est = max(-self._max_speed, min(self._max_speed, v))
        else:  # the first set-point, or the first after a gap: no speed known
            self._v_est = 0.0
        self._sp = value
        self._sp_at = at_ns
        self._have_sp = True

    def update(self, now_ns: int, dt: float) -> float:
        """Advance the reference to ``now_ns`` (``dt`` seconds after the previous call)."""
        if self._following and self._have_sp:
            ahead = min(max(0, now_ns - self._sp_at), self._max_extra)
            target = self._sp + self._v_est * ahead * 1e-9
            target_speed = self._v_est if now_ns - self._sp_at < self._max_extra else 0.0
        else:
            target = self._hold
            target_speed = 0.0
        low, high = self._limits
        if target < low or target > high:
            target = min(max(target, low), high)
            target_speed = 0.0
        step = target - self.reference
        max_step = self._max_speed * dt
        if abs(step) > max_step:
            self.reference += math.copysign(max_step, step)
            self.speed = math.copysign(self._max_speed, step)
        else:
            self.reference = target
            self.speed = target_speed
        return self.reference


class AxisController:
    """PID with velocity feed-forward for one axis; see the module docstring."""

    __slots__ = ("_angle", "_gains", "_integral", "_started", "duty", "speed_estimate")

    def __init__(self, gains: Gains) -> None:
        self._gains = gains
        self._integral = 0.0
        self._angle = 0.0
        self._started = False
        #: The last duty commanded (saturated) and the filtered encoder speed (rad/s).
        self.duty = 0.0
        self.speed_estimate = 0.0

    def reset(self, angle: float) -> None:
        """Bumpless start at ``angle``: no integral, no speed."""
        self._integral = 0.0
        self._angle = angle
        self._started = True
        self.speed_estimate = 0.0
        self.duty = 0.0

    def update(self, reference: float, ref_speed: float, angle: float, dt: float) -> float:
        """One cycle: measured ``angle`` in, duty in [-1, 1] out."""
        g = self._gains
        if not self._started:
            self.reset(angle)
        raw_speed = (angle - self._angle) / dt
        self._angle = angle
        self.speed_estimate += dt / (g.speed_filter + dt) * (raw_speed - self.speed_estimate)
        error = reference - angle
        if abs(error) < 0.5 * RAD_PER_COUNT:  # inside one encoder count: nothing to correct
            error = 0.0
        unsaturated = (g.kff * ref_speed + g.kp * error
                       + g.kd * (ref_speed - self.speed_estimate) + self._integral)
        pushing_further = (unsaturated > 1.0 and error > 0) or (unsaturated < -1.0 and error < 0)
        if not pushing_further:
            limit = g.integral_limit
            self._integral = max(-limit, min(limit, self._integral + g.ki * error * dt))
        self.duty = max(-1.0, min(1.0, unsaturated))
        return self.duty
