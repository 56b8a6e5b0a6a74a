"""The pan-tilt demo's topics and the diagnostics message, shared by both sides of the bridge.

Topic layout follows thesis figure 3.2, with one ``std_msgs/msg/Float64`` topic per axis so that
any ROS 2 tool (``ros2 topic echo``, rqt_plot) shows them without custom messages:

========================== ===================== ========= ================================
topic                      type                  transport who writes
========================== ===================== ========= ================================
``<ns>/pan/setpoint``      ``std_msgs/Float64``  UDP       vision node, 30 Hz (frame rate)
``<ns>/tilt/setpoint``     ``std_msgs/Float64``  UDP       vision node, 30 Hz
``<ns>/pan/angle``         ``std_msgs/Float64``  UDP       controller, sub-sampled to 50 Hz
``<ns>/tilt/angle``        ``std_msgs/Float64``  UDP       controller, sub-sampled to 50 Hz
``<ns>/status``            ``std_msgs/String``   TCP       controller, when its state changes
``<ns>/diagnostics``       ``std_msgs/String``   TCP       controller, 5 Hz, JSON
========================== ===================== ========= ================================

Set-points and angles go over UDP: a newer value makes an older one worthless, so a lost
datagram costs one sample while a TCP retransmission would delay every later one (thesis 3.3.1).
Status and diagnostics are sporadic and must arrive, so they go over TCP. Diagnostics would be a
``diagnostic_msgs/DiagnosticArray`` in a ROS-only system; the in-process bus knows std_msgs and
geometry_msgs only, so the demo sends a JSON string (:class:`Diagnostics`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from typing import Any

FLOAT64 = "std_msgs/msg/Float64"
STRING = "std_msgs/msg/String"
DEFAULT_NAMESPACE = "/pan_tilt"


@dataclass(frozen=True, slots=True)
class Topics:
    """Topic names under one namespace (``/pan_tilt`` unless told otherwise)."""

    namespace: str = DEFAULT_NAMESPACE

    def _name(self, suffix: str) -> str:
        return f"{self.namespace.rstrip('/')}/{suffix}"

    def setpoint(self, axis: str) -> str:
        return self._name(f"{axis}/setpoint")

    def angle(self, axis: str) -> str:
        return self._name(f"{axis}/angle")

    @property
    def status(self) -> str:
        return self._name("status")

    @property
    def diagnostics(self) -> str:
        return self._name("diagnostics")


AXES = ("pan", "tilt")


@dataclass(frozen=True, slots=True)
class Diagnostics:
    """The controller's health, as the middleware sees it (JSON in a ``std_msgs/String``)."""

    state: str = "idle"
    link: str = "connected"
    scheduling: str = "unknown"
    cycles: int = 0
    missed: int = 0
    late_p50_us: float = 0.0
    late_p99_us: float = 0.0
    late_max_us: float = 0.0
    setpoints_received: int = 0
    setpoints_lost: int = 0
    setpoint_age_ms: float = -1.0
    angles_sent: int = 0
    #: This controller process (a random id) and its session with the bridge (0 the first,
    #: +1 per reconnect), and the angles sent in that session: a restarted bridge's monitor
    #: counts only what was sent to it (``Trace.angles_sent``), not what the previous got.
    run: str = ""
    session: int = 0
    angles_sent_session: int = 0
    #: When it was written, in the bridge's wall clock (the SDK's clock-offset estimate): a
    #: message written to a previous bridge and delivered to a restarted one is older than it.
    written_ns: int = 0
    error_rms_mrad: tuple[float, float] = (math.nan, math.nan)
    error_max_mrad: tuple[float, float] = (math.nan, math.nan)
    hrt_blocking_reads: int = 0

    def to_json(self) -> str:
        return json.dumps(asdict(self), allow_nan=True, separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str) -> Diagnostics:
        """Parse; unknown keys (a newer controller) are ignored, missing ones take defaults."""
        raw: dict[str, Any] = json.loads(text)
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in raw.items() if k in known}
        for key in ("error_rms_mrad", "error_max_mrad"):
            if key in values:
                values[key] = tuple(values[key])
        return cls(**values)
