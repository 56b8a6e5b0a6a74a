"""The book a load client keeps per session, and the topics it uses: shared by both kinds.

The SDK sessions (:mod:`.load_roles`) and the protocol-level ones (:mod:`.load_raw`) count and
sample the same way, so the parent reads one report whatever ``--client`` ran.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from array import array

from rlbridge.bench.common import Params, percentile

F64 = "std_msgs/msg/Float64"


def topic(session: int, channel: int) -> str:
    return f"/load/s{session}/c{channel}"


class Book(ABC):
    """A session's counters and latency samples, cut into the phases the parent announces."""

    def __init__(self, index: int, phase: list[str]) -> None:
        self.index = index
        self.sent = 0
        self.latency: dict[str, array[float]] = {}
        self.marks: list[tuple[str, int, int, float]] = []  # phase, sent, received, time
        self._phase = phase

    @abstractmethod
    def received(self) -> int:
        """Values this session has received so far (each client kind counts its own way)."""

    def extra(self) -> Params:
        return {}

    def record(self, latency_us: float) -> None:
        phase = self._phase[0]
        samples = self.latency.get(phase)
        if samples is None:
            samples = self.latency[phase] = array("f")
        samples.append(latency_us)

    def mark(self, phase: str) -> None:
        self.marks.append((phase, self.sent, self.received(), time.monotonic()))

    def result(self) -> Params:
        """Per-phase sent/received and latency percentiles (µs), and the run's losses."""
        self.mark("end")
        phases: dict[str, Params] = {}
        for (name, s0, r0, t0), (_n, s1, r1, t1) in zip(self.marks, self.marks[1:],
                                                         strict=False):
            lat = sorted(self.latency.get(name, []))
            phases[name] = {"sent": s1 - s0, "received": r1 - r0, "seconds": t1 - t0,
                            "n": len(lat), "p50": percentile(lat, 50),
                            "p99": percentile(lat, 99)}
        return {"session": self.index, "sent": self.sent, "received": self.received(),
                "phases": phases, **self.extra()}
