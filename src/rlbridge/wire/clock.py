"""Clock offset between two hosts, and interarrival jitter: pure arithmetic on timestamps.

Theory of operation. A value's age is ``receiver's now - sender's stamp``, which mixes two
clocks. :class:`ClockOffset` estimates ``offset = peer clock - our clock`` NTP-style (RFC 5905,
section 8) from heartbeat exchanges: we sent at ``t1`` (our wall clock), the peer received at
``t2`` and answered at ``t3`` (its wall clock), we received at ``t4``. Then

    offset = ((t2 - t1) + (t3 - t4)) / 2        delay = (t4 - t1) - (t3 - t2)

and the error of ``offset`` is at most ``delay / 2`` (the true value lies in
``[t2 - t1 - delay, t2 - t1]`` shifted symmetrically; any asymmetry of the two path delays
appears as error, never more than half the round trip). Queueing inflates ``delay`` and
skews the sample, so like NTP's clock filter we keep the last ``window`` samples and trust
the one with the smallest delay: its error bound is the smallest. The window slides, so a
clock that drifts (or is stepped) is followed within ``window`` heartbeats.

:class:`InterarrivalJitter` is RFC 3550's (section 6.4.1, A.8) estimator, in ns: for each
value, ``D = (arrival - stamp) - (previous arrival - previous stamp)`` and
``J += (|D| - J) / 16``. It needs no clock synchronisation: the offset cancels in ``D``.
:func:`moving_average` is that estimator's step, also used for a channel's one-way age.

No clocks are read here (sans-IO): callers pass times in.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

#: Heartbeat exchanges the minimum-delay filter looks back over (NTP uses 8).
CLOCK_WINDOW = 8


def moving_average(average: int, sample: int) -> int:
    """RFC 3550's smoothing step (gain 1/16), in integers; a negative ``average``: none yet.

    The value paths copy this expression inline (one Python call per value saved); each copy
    names it in an inlines tag, and a parity test keeps the copy equal to it.
    """
    return sample if average < 0 else average + (sample - average) // 16


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One exchange: the peer's clock minus ours, and the round trip it was measured over."""

    offset_ns: int
    delay_ns: int


class ClockOffset:
    """Minimum-delay filter over the last ``window`` NTP-style samples (module docstring)."""

    __slots__ = ("_samples", "error_bound_ns", "offset_ns", "samples_taken")

    def __init__(self, window: int = CLOCK_WINDOW) -> None:
        if window < 1:
            raise ValueError(f"clock filter window must be >= 1, got {window}")
        self._samples: deque[ClockSample] = deque(maxlen=window)
        #: Peer clock minus our clock (0 until the first exchange). Plain attributes, not
        #: properties: readers on a control loop's hot path pay one attribute load.
        self.offset_ns = 0
        #: How far :attr:`offset_ns` can be off: half the filtered round trip (-1: unknown).
        self.error_bound_ns = -1
        self.samples_taken = 0

    def add(self, t1: int, t2: int, t3: int, t4: int) -> ClockSample | None:
        """Feed one exchange (see module docstring); returns the sample, or None if absurd.

        An exchange whose round trip comes out negative (a clock stepped in between, or the
        peer's hold time larger than our whole round trip) says nothing and is ignored.
        """
        delay = (t4 - t1) - (t3 - t2)
        if delay < 0 or t4 < t1:
            return None
        sample = ClockSample(((t2 - t1) + (t3 - t4)) // 2, delay)
        self._samples.append(sample)
        best = min(self._samples, key=lambda s: s.delay_ns)
        # Two single stores: a reader on another thread may pair a new offset with the
        # previous bound for a moment (one sample apart), never a torn number.
        self.offset_ns = best.offset_ns
        self.error_bound_ns = best.delay_ns // 2
        self.samples_taken += 1
        return sample

    @property
    def known(self) -> bool:
        return self.error_bound_ns >= 0


class InterarrivalJitter:
    """RFC 3550 interarrival jitter in ns (module docstring); ``jitter_ns`` is the estimate."""

    __slots__ = ("jitter_ns", "last_transit")

    def __init__(self) -> None:
        #: The previous value's transit time (public: the server's value path inlines ``add``).
        self.last_transit: int | None = None
        self.jitter_ns = 0

    def add(self, stamp_ns: int, arrival_ns: int) -> None:
        transit = arrival_ns - stamp_ns
        last = self.last_transit
        self.last_transit = transit
        # inlines: moving_average
        if last is not None:  # jitter_ns starts at 0 and never goes below it
            self.jitter_ns += (abs(transit - last) - self.jitter_ns) // 16
