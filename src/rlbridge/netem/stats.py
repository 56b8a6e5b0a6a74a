"""Counters for the relay, so that no packet the emulator drops goes unrecorded.

The relay process owns a mutable :class:`DirectionCounters` per direction and sends
immutable :class:`DirectionStats` snapshots over the control channel when asked.
``late_*`` measure the relay itself: how long after its scheduled release time a packet
was actually written to the receiving TUN (timer wake-up plus Python overhead).  That is
the part of the measured latency the emulator adds on top of the configured delay.  A
benchmark should check them (for instance ``late_over_1ms == 0``) before trusting a run
on a busy machine: a late relay looks exactly like a slow network.
"""

from __future__ import annotations

import msgspec

from rlbridge.netem.impairment import DropReason


class DirectionStats(msgspec.Struct, frozen=True, kw_only=True):
    """A snapshot of one direction's counters.

    ``received`` counts packets the relay read from the sending namespace; packets the
    kernel dropped before that (a full TUN transmit queue) are not seen by the relay.
    """

    received: int = 0
    delivered: int = 0
    dropped_loss: int = 0
    dropped_queue: int = 0
    write_errors: int = 0
    bytes_received: int = 0
    bytes_delivered: int = 0
    in_flight: int = 0
    late_max_us: float = 0.0
    late_mean_us: float = 0.0
    late_over_100us: int = 0
    late_over_1ms: int = 0
    late_over_10ms: int = 0

    @property
    def dropped(self) -> int:
        """All packets this direction dropped on purpose (loss model and queue limit)."""
        return self.dropped_loss + self.dropped_queue


class LinkStats(msgspec.Struct, frozen=True, kw_only=True):
    """Both directions of the link."""

    a_to_b: DirectionStats
    b_to_a: DirectionStats


_LATE_THRESHOLDS_S = (100e-6, 1e-3, 10e-3)


class DirectionCounters:
    """Mutable counters the relay updates per packet; :meth:`snapshot` freezes them."""

    def __init__(self) -> None:
        self.received = 0
        self.delivered = 0
        self.dropped_loss = 0
        self.dropped_queue = 0
        self.write_errors = 0
        self.bytes_received = 0
        self.bytes_delivered = 0
        self.in_flight = 0
        self._late_max = 0.0
        self._late_sum = 0.0
        self._late_over = [0, 0, 0]  # > 100 us, > 1 ms, > 10 ms

    def on_received(self, size: int) -> None:
        """A packet was read from the sending TUN."""
        self.received += 1
        self.bytes_received += size

    def on_dropped(self, reason: DropReason) -> None:
        """The model dropped the packet just received."""
        if reason is DropReason.LOSS:
            self.dropped_loss += 1
        else:
            self.dropped_queue += 1

    def on_scheduled(self) -> None:
        """The packet just received waits for its release time."""
        self.in_flight += 1

    def on_released(self, size: int, late_s: float, *, ok: bool) -> None:
        """A packet left the heap ``late_s`` seconds after its release time."""
        self.in_flight -= 1
        if not ok:
            self.write_errors += 1
            return
        self.delivered += 1
        self.bytes_delivered += size
        self._late_sum += late_s
        self._late_max = max(self._late_max, late_s)
        for i, threshold in enumerate(_LATE_THRESHOLDS_S):
            if late_s > threshold:
                self._late_over[i] += 1

    def snapshot(self) -> DirectionStats:
        """An immutable copy, with lateness in microseconds."""
        mean = self._late_sum / self.delivered if self.delivered else 0.0
        return DirectionStats(
            received=self.received,
            delivered=self.delivered,
            dropped_loss=self.dropped_loss,
            dropped_queue=self.dropped_queue,
            write_errors=self.write_errors,
            bytes_received=self.bytes_received,
            bytes_delivered=self.bytes_delivered,
            in_flight=self.in_flight,
            late_max_us=self._late_max * 1e6,
            late_mean_us=mean * 1e6,
            late_over_100us=self._late_over[0],
            late_over_1ms=self._late_over[1],
            late_over_10ms=self._late_over[2],
        )
