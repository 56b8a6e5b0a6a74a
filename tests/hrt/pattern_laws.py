"""Control laws for loops in their own process: module-level, so that they pickle.

The loop process imports this module by name (``spawn`` passes the test run's ``sys.path``);
a law's state lives there and comes back as ``IsolatedCoupling.final_control``.
"""

from __future__ import annotations

import os


class Recorder:
    """Receive law: the distinct values it read, in order, and the process it ran in."""

    def __init__(self) -> None:
        self.values: list[float] = []
        self.pid: int | None = None

    def __call__(self, value: float) -> None:
        self.pid = os.getpid()
        if not self.values or self.values[-1] != value:
            self.values.append(value)


class Counter:
    """Send law: 1.0, 2.0, 3.0, ... one per release."""

    def __init__(self) -> None:
        self.k = 0

    def __call__(self) -> float:
        self.k += 1
        return float(self.k)


class FailsAt:
    """Send law that raises on its ``n``-th call: a bug in the control code."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.calls = 0

    def __call__(self) -> float:
        self.calls += 1
        if self.calls >= self.n:
            raise ZeroDivisionError(f"control law bug at release {self.calls}")
        return 0.0


def not_a_number() -> object:
    """Send law whose value cannot cross as float64."""
    return "north"


def double(value: float) -> float:
    """``process=`` step of the blocking receive, run by the SRT helper."""
    return 2 * value
