"""The middleware side's view of the camera: what ROS would visualize (thesis fig. 3.2).

:class:`Trace` records, on one clock, every set-point the vision node published and every
angle, status and diagnostics message the controller sent back. :class:`Monitor` is the node
that subscribes to the controller's topics and feeds the trace. The dashboard, the plot and
the tracking metrics are all computed from a :meth:`Trace.snapshot`, so they show exactly what
a middleware user would see, in every role of the demo.

Subscription callbacks run on the adapter's delivery thread (the server's event loop for the
in-process bus, the executor thread for ROS 2); they only append under a lock.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, TypeVar

from rlbridge.adapters.base import MiddlewareAdapter, QoS, Subscription
from rlbridge.demo.topics import AXES, FLOAT64, STRING, Diagnostics, Topics


@dataclass(frozen=True)
class TraceSnapshot:
    """A consistent copy of a :class:`Trace`; times are seconds since the trace started."""

    elapsed: float
    setpoints: list[tuple[float, float, float]] = field(default_factory=list)
    """``(t, pan, tilt)`` per published frame."""
    angles: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    """Per axis, ``(t, angle)`` per received value."""
    statuses: list[tuple[float, str]] = field(default_factory=list)
    diagnostics: Diagnostics | None = None
    diagnostics_at: float = -1.0
    angles_total: dict[str, int] = field(default_factory=dict)
    """Per axis, every angle received since the start (also those no longer in ``angles``)."""
    setpoints_total: int = 0
    angles_sent: int = 0
    """Angles the controller sent to *this* bridge: the sum over its sessions with it, as each
    last reported (a session with a bridge that ran before this one is not counted)."""

    @property
    def angles_lost(self) -> int:
        """Angles sent to this bridge that never arrived (live: may count some in flight)."""
        return max(0, self.angles_sent - sum(self.angles_total.values()))


#: The state the bridge side records when the controller's session with its server closes:
#: not one the controller reports (it cannot report its own absence), so the trace says it.
GONE = "gone"

_T = TypeVar("_T", bound=tuple[float, ...])


def _since(samples: deque[_T], since: float) -> list[_T]:
    """The samples (tuples starting with their time) at or after ``since``."""
    if since < 0:
        return list(samples)
    out: list[_T] = []
    for sample in reversed(samples):
        if sample[0] < since:
            break
        out.append(sample)
    out.reverse()
    return out


class Trace:
    """Thread-safe recorder; see the module docstring.

    Samples older than ``keep`` seconds are dropped (a bridge that runs for days must not grow
    without bound); statuses are few and all kept.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, keep: float = 600.0,
                 wall: Callable[[], int] = time.time_ns) -> None:
        self._clock = clock
        self._t0 = clock()
        #: Diagnostics written before this (wall clock) describe a bridge that ran before.
        self._started_ns = wall()
        self.stale_diagnostics = 0
        self._cond = threading.Condition()
        frames = int(keep * 30) + 1
        values = int(keep * 50) + 1
        self._setpoints: deque[tuple[float, float, float]] = deque(maxlen=frames)
        self._angles: dict[str, deque[tuple[float, float]]] = {
            axis: deque(maxlen=values) for axis in AXES}
        self._statuses: list[tuple[float, str]] = []
        self._diag: Diagnostics | None = None
        self._diag_at = -1.0
        self._setpoint_count = 0
        self._counts = dict.fromkeys(AXES, 0)
        #: Angles sent per controller session, keyed by (controller run, session number).
        self._sent: dict[tuple[str, int], int] = {}

    def now(self) -> float:
        """Seconds since the trace started."""
        return self._clock() - self._t0

    def add_setpoint(self, t: float, pan: float, tilt: float) -> None:
        with self._cond:
            self._setpoints.append((t, pan, tilt))
            self._setpoint_count += 1

    def add_angles(self, axis: str, values: list[float]) -> None:
        t = self.now()
        with self._cond:
            self._angles[axis].extend((t, v) for v in values)
            self._counts[axis] += len(values)

    def add_status(self, status: str) -> None:
        t = self.now()
        with self._cond:
            self._statuses.append((t, status))
            self._cond.notify_all()

    def controller_left(self) -> None:
        """The controller's session with the server closed (its last status and diagnostics
        describe it as it was, not as it is): record the state :data:`GONE`."""
        self.add_status(GONE)

    def set_diagnostics(self, diag: Diagnostics) -> None:
        t = self.now()
        with self._cond:
            if 0 < diag.written_ns < self._started_ns:  # waited in the SDK across a restart
                self.stale_diagnostics += 1
                return
            self._diag, self._diag_at = diag, t
            self._sent[(diag.run, diag.session)] = diag.angles_sent_session
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[TraceSnapshot], bool], timeout: float) -> bool:
        """Block until ``predicate(snapshot)`` holds (re-checked on each status/diagnostics)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(self._snapshot_locked()):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True

    def snapshot(self, last: float | None = None) -> TraceSnapshot:
        """A copy of everything, or of the samples of the ``last`` seconds only."""
        with self._cond:
            return self._snapshot_locked(last)

    def _snapshot_locked(self, last: float | None = None) -> TraceSnapshot:
        now = self.now()
        since = -1.0 if last is None else now - last
        return TraceSnapshot(
            elapsed=now,
            setpoints=_since(self._setpoints, since),
            angles={axis: _since(values, since) for axis, values in self._angles.items()},
            statuses=list(self._statuses),
            diagnostics=self._diag,
            diagnostics_at=self._diag_at,
            angles_total={axis: self._counts[axis] for axis in AXES},
            setpoints_total=self._setpoint_count,
            angles_sent=sum(self._sent.values()),
        )


class Monitor:
    """Subscribes to the controller's angles, status and diagnostics; records them in a trace."""

    def __init__(self, adapter: MiddlewareAdapter, trace: Trace, *,
                 topics: Topics | None = None) -> None:
        t = topics or Topics()
        self.trace = trace
        self.bad_diagnostics = 0
        self._subs: list[Subscription] = []
        try:
            for axis in AXES:
                self._subs.append(adapter.subscribe(
                    t.angle(axis), FLOAT64, "data", QoS("best_effort", 50),
                    partial(self._on_angles, axis)))
            self._subs.append(adapter.subscribe(t.status, STRING, "data", QoS("reliable", 50),
                                                self._on_status))
            self._subs.append(adapter.subscribe(t.diagnostics, STRING, "data",
                                                QoS("reliable", 10), self._on_diagnostics))
        except BaseException:
            self.close()
            raise

    def _on_angles(self, axis: str, values: Any) -> None:
        self.trace.add_angles(axis, [float(v) for v in values])

    def _on_status(self, values: Any) -> None:
        for value in values:
            self.trace.add_status(str(value))

    def _on_diagnostics(self, values: Any) -> None:
        for value in values:
            try:
                diag = Diagnostics.from_json(str(value))
            except (ValueError, TypeError):  # not our controller's JSON: count, do not crash
                self.bad_diagnostics += 1
                continue
            self.trace.set_diagnostics(diag)

    def close(self) -> None:
        """Unsubscribe everything; idempotent."""
        subs, self._subs = self._subs, []
        for sub in subs:
            sub.close()

