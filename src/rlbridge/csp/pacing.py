"""How many of an outgoing channel's waiting values may leave now: credit and a rate limit.

Theory of operation. The send thread asks :meth:`Pacing.allowance` before it drains a
channel's ring and takes at most that many values; the rest stay in the ring, where the
channel's overflow policy (drop the oldest, counted in ``overwritten``) applies *at the
source*, in the control code's own process, instead of as silent loss further on.

Two limits, either or both:

* **Credit** (TCP channels that promise every value, docs/policies.md): the server grants
  ``limit``, the sequence number the channel may send up to (``TopicAck.credit``, then
  ``Credit`` packets as the subscribers consume); ``None`` means no flow control.
* **Rate** (``publish(..., policy=Policy(max_rate_hz=...))``): a token bucket refilled at
  ``rate_hz`` that holds at most :data:`BURST_S` seconds' worth. With ``adapt=True``
  (``adapt_rate``) the rate follows the server's loss reports: halved when a report shows more
  than :data:`LOSS_TOLERANCE` of the values lost at the first hop, raised by :data:`GROWTH`
  (5 %) after a report without loss, never above ``max_rate_hz``. A constant step (TCP's
  additive increase) would have to be sized to the path; a relative one finds the path's rate
  from any start, in a few reports.

Pure bookkeeping: time is a parameter (``now_ns``), no thread, lock or clock here.
"""

from __future__ import annotations

#: Most values the bucket holds: this many seconds at the current rate (at least one value).
BURST_S = 0.005
#: A report losing more than this fraction of its values halves an adaptive rate.
LOSS_TOLERANCE = 0.01
#: How much an adaptive rate grows after a report without loss.
GROWTH = 0.05
#: An adaptive rate never goes below this fraction of its maximum.
MIN_RATE_FRACTION = 1 / 256
#: Stands for "no limit" in :meth:`Pacing.allowance`.
UNLIMITED = 1 << 62


class Pacing:
    """Credit and rate limit of one outgoing channel; see the module docstring."""

    __slots__ = ("_at", "_tokens", "adapt", "limit", "max_rate_hz", "rate_hz")

    def __init__(self, max_rate_hz: float | None = None, *, adapt: bool = False,
                 now_ns: int = 0) -> None:
        if max_rate_hz is not None and not max_rate_hz > 0:
            raise ValueError(f"max_rate_hz must be positive, got {max_rate_hz}")
        if adapt and max_rate_hz is None:
            raise ValueError("adapt_rate needs max_rate_hz: the rate it starts from and "
                             "never exceeds")
        self.max_rate_hz = max_rate_hz
        #: The rate in force now (adaptive rates move between a floor and ``max_rate_hz``).
        self.rate_hz = max_rate_hz
        self.adapt = adapt
        #: Credit: values numbered below this may be sent; None: not flow-controlled.
        self.limit: int | None = None
        self._tokens = self._burst()
        self._at = now_ns

    def _burst(self) -> float:
        rate = self.rate_hz
        return 0.0 if rate is None else max(1.0, rate * BURST_S)

    def _refill(self, now_ns: int) -> None:
        rate = self.rate_hz
        if rate is not None and now_ns > self._at:
            self._tokens = min(self._burst(), self._tokens + (now_ns - self._at) * rate / 1e9)
        self._at = max(self._at, now_ns)

    def allowance(self, next_seq: int, now_ns: int) -> int:
        """Values that may be taken now, the next one being numbered ``next_seq``."""
        n = UNLIMITED
        if self.rate_hz is not None:
            self._refill(now_ns)
            n = int(self._tokens)
        if self.limit is not None:
            n = min(n, self.limit - next_seq)
        return max(0, n)

    def spend(self, n: int) -> None:
        """``n`` values were taken (after :meth:`allowance` said they may)."""
        if self.rate_hz is not None:
            self._tokens -= n

    def wait_s(self, now_ns: int) -> float | None:
        """Seconds until the rate allows one more value; None when only credit can help."""
        rate = self.rate_hz
        if rate is None:
            return None
        self._refill(now_ns)
        return max(0.0, (1.0 - self._tokens) / rate)

    def on_credit(self, limit: int) -> bool:
        """The server granted credit up to ``limit``; True if that is more than before."""
        if self.limit is not None and limit <= self.limit:
            return False
        self.limit = limit
        return True

    def on_report(self, received: int, lost: int) -> None:
        """A loss report: ``received`` and ``lost`` values since the previous one (AIMD)."""
        if not self.adapt or self.max_rate_hz is None or self.rate_hz is None:
            return
        total = received + lost
        if total <= 0:
            return
        top = self.max_rate_hz
        if lost > LOSS_TOLERANCE * total:
            self.rate_hz = max(top * MIN_RATE_FRACTION, self.rate_hz / 2)
        else:
            self.rate_hz = min(top, self.rate_hz * (1 + GROWTH) + 1)
        self._tokens = min(self._tokens, self._burst())
