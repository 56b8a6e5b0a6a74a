"""A simulated two-axis pan-tilt camera: the "hardware" the demo's loop controller drives.

Each axis is a DC motor with a gearbox driving an inertia, with viscous friction, a saturating
PWM input in [-1, 1] and an incremental encoder (4096 counts per revolution). The tilt axis also
carries an unbalanced camera (a gravity torque), which is what makes integral action useful.

Theory of operation
-------------------
Per axis, with the motor's inductance neglected (its electrical time constant is far below the
1 ms control period): ``J dw/dt = K/R (u V - K w) - b w - T_g cos(theta)``, so the speed is a
first-order system with time constant ``J / D`` (``D = b + K^2 / R``) and steady-state speed
``(K V u / R - T_g cos(theta)) / D``. Over a step the input is constant (zero-order hold, as a
PWM register is), so the speed update uses the exact exponential solution and the angle the
trapezoid rule; steps are at most ``max_step`` long, so a late control cycle only means that
the PWM value was held for longer, exactly as on a real board.

Time is a parameter: :meth:`PanTiltPlant.sample` takes ``now_ns`` and advances the physics to
it, so tests drive the plant with a fake clock and the demo with ``time.monotonic_ns``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

COUNTS_PER_REV = 4096
"""Encoder resolution: one count is 2*pi/4096 = 1.53 mrad."""

RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV


@dataclass(frozen=True, slots=True)
class AxisParams:
    """Physical parameters of one axis, referred to the output shaft (after the gearbox)."""

    inertia: float = 0.0075
    """J in kg m^2: camera, bracket and the reflected rotor inertia."""
    viscous: float = 0.01
    """b in N m s/rad: bearing and gearbox friction."""
    motor_constant: float = 0.75
    """K in N m/A = V s/rad (torque and back-EMF constant, gear ratio included)."""
    resistance: float = 4.0
    """R in ohm."""
    supply: float = 12.0
    """V: the voltage a PWM duty of 1.0 applies."""
    unbalance: float = 0.0
    """T_g in N m: gravity torque of an off-centre load, ``T_g cos(theta)``."""

    @property
    def damping(self) -> float:
        """D = b + K^2/R: viscous friction plus back-EMF braking."""
        return self.viscous + self.motor_constant**2 / self.resistance

    @property
    def time_constant(self) -> float:
        """Mechanical time constant J/D in seconds."""
        return self.inertia / self.damping

    @property
    def torque_per_duty(self) -> float:
        """Stall torque at full duty, K V / R, in N m."""
        return self.motor_constant * self.supply / self.resistance

    @property
    def max_speed(self) -> float:
        """Unloaded speed at full duty in rad/s."""
        return self.torque_per_duty / self.damping


PAN = AxisParams()
TILT = AxisParams(inertia=0.0060, unbalance=0.2)


class Axis:
    """One motor + inertia; state is angle (rad) and speed (rad/s)."""

    __slots__ = ("angle", "duty", "params", "speed")

    def __init__(self, params: AxisParams, angle: float = 0.0) -> None:
        self.params = params
        self.angle = angle
        self.speed = 0.0
        self.duty = 0.0

    def step(self, dt: float) -> None:
        """Advance ``dt`` seconds with the current duty held."""
        p = self.params
        damping = p.damping
        torque = p.torque_per_duty * self.duty - p.unbalance * math.cos(self.angle)
        steady = torque / damping
        decay = math.exp(-dt * damping / p.inertia)
        speed0 = self.speed
        speed1 = steady + (speed0 - steady) * decay
        self.angle += 0.5 * (speed0 + speed1) * dt
        self.speed = speed1

    def encoder(self) -> int:
        """Encoder counts: the angle quantized towards minus infinity, as a counter does."""
        return math.floor(self.angle / RAD_PER_COUNT)


class PanTiltPlant:
    """Two axes advanced together in real (or fake) time; see the module docstring."""

    def __init__(self, pan: AxisParams = PAN, tilt: AxisParams = TILT, *,
                 max_step: float = 0.0005) -> None:
        if max_step <= 0:
            raise ValueError(f"max_step must be positive, got {max_step}")
        self.pan = Axis(pan)
        self.tilt = Axis(tilt)
        self._max_step = max_step
        self._t_ns: int | None = None

    def sample(self, now_ns: int) -> tuple[int, int]:
        """Advance the physics to ``now_ns`` and read both encoders (pan, tilt) in counts."""
        self.advance(now_ns)
        return self.pan.encoder(), self.tilt.encoder()

    def actuate(self, pan_duty: float, tilt_duty: float) -> tuple[float, float]:
        """Set both PWM duties, saturated to [-1, 1] as the hardware does; returns what was set."""
        self.pan.duty = _saturate(pan_duty)
        self.tilt.duty = _saturate(tilt_duty)
        return self.pan.duty, self.tilt.duty

    def advance(self, now_ns: int) -> None:
        """Integrate from the last call to ``now_ns`` (the first call only sets the time)."""
        last = self._t_ns
        self._t_ns = now_ns
        if last is None or now_ns <= last:
            return
        remaining = (now_ns - last) * 1e-9
        steps = max(1, math.ceil(remaining / self._max_step))
        dt = remaining / steps
        for _ in range(steps):
            self.pan.step(dt)
            self.tilt.step(dt)


def counts_to_rad(counts: int) -> float:
    """Encoder counts to radians."""
    return counts * RAD_PER_COUNT


def _saturate(duty: float) -> float:
    if math.isnan(duty):  # a broken control law must not drive the motor
        return 0.0
    return 1.0 if duty > 1.0 else -1.0 if duty < -1.0 else duty
