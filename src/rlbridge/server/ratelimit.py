"""Values per second per session (``--max-rate``): a token bucket, time passed in.

The bucket holds up to one second of values, so a client may burst (a batch after a pause)
but not exceed the rate on average. Values over the limit are dropped and counted; the client
hears about it at most once per second (``should_warn``), never once per value, so a flood of
refusals cannot itself become the flood.
"""

from __future__ import annotations

WARN_EVERY_NS = 1_000_000_000


class RateLimiter:
    """Admit values at ``rate`` per second on average; ``dropped`` counts what was refused."""

    def __init__(self, rate: float, now_ns: int) -> None:
        if rate <= 0:
            raise ValueError("rate must be positive")
        self.rate = rate
        self._capacity = max(1.0, rate)
        self._tokens = self._capacity
        self._last = now_ns
        self._warned = now_ns - WARN_EVERY_NS
        self.dropped = 0

    def admit(self, n: int, now_ns: int) -> int:
        """How many of ``n`` values may pass now (the first ones); the rest count as dropped."""
        elapsed = max(0, now_ns - self._last)
        self._last = now_ns
        self._tokens = min(self._capacity, self._tokens + elapsed * self.rate / 1e9)
        ok = min(n, int(self._tokens))
        self._tokens -= ok
        self.dropped += n - ok
        return ok

    def should_warn(self, now_ns: int) -> bool:
        """True at most once per second: time to tell the client it is being limited."""
        if now_ns - self._warned < WARN_EVERY_NS:
            return False
        self._warned = now_ns
        return True
