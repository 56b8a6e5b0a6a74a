"""The pure impairment model: what happens to one packet on one direction of the link.

Theory of operation
-------------------
``tc ... netem`` (which the thesis used, listings A.1/A.2) decides, per packet, at enqueue
time, whether the packet is lost and when it leaves the queue.  :class:`PathModel` does
the same thing for one direction of an :class:`~rlbridge.netem.link.EmulatedLink`, with no
sockets, threads or clocks: the caller passes ``now`` (seconds, any monotonic origin) and
the packet size, and gets back either the time at which the packet must be released or
the reason it was dropped.  The relay process owns the clock and the timer heap; tests
drive the model with a fake clock.

Per packet, in this order:

1. **Loss** -- a Bernoulli draw with ``loss_pct``, or a Gilbert-Elliott two-state chain
   (``bursts``) for correlated loss.  Loss draws come from their own RNG, so the set of
   lost packets depends only on the seed and the packet index in this direction: changing
   the delay or jitter of a run does not change which packets are lost.
2. **Queue limit** -- at most ``limit`` packets in flight per direction (netem's
   ``limit``); beyond that the packet is tail-dropped.
3. **Rate** -- with ``rate_kbit`` the packet is serialised after the ones before it
   (``size * 8 / rate``), like netem's ``rate``.
4. **Delay** -- ``delay_ms`` plus a uniform jitter in ``[-jitter_ms, +jitter_ms]`` (netem's
   default distribution), clamped at zero.  Unless ``reorder`` is set, a packet is never
   released before the one admitted just before it, because real paths rarely reorder and
   a reordering emulator would test TCP's reordering heuristics instead of the bridge.

Each direction has its own :class:`PathModel` and its own RNGs, so traffic in one
direction never changes the loss pattern of the other.
"""

from __future__ import annotations

import enum
import heapq
import random
from typing import Literal

import msgspec

Direction = Literal["both", "a_to_b", "b_to_a"]
"""Which direction(s) of the link an impairment applies to."""

DIRECTIONS: tuple[Direction, ...] = ("both", "a_to_b", "b_to_a")


class DropReason(enum.Enum):
    """Why the model dropped a packet; each reason has its own counter in the stats."""

    LOSS = "loss"
    QUEUE_FULL = "queue_full"


class GilbertElliott(msgspec.Struct, frozen=True, kw_only=True):
    """Two-state (good/bad) Markov loss model, as netem's ``loss gemodel p r 1-h 1-k``.

    All values are percentages.  The chain steps once per packet.  The long-run loss rate
    is ``pi_bad * loss_in_bad_pct + (1 - pi_bad) * loss_in_good_pct`` with
    ``pi_bad = enter_bad_pct / (enter_bad_pct + leave_bad_pct)``; the mean burst length
    in the bad state is ``100 / leave_bad_pct`` packets.
    """

    enter_bad_pct: float
    leave_bad_pct: float
    loss_in_bad_pct: float = 100.0
    loss_in_good_pct: float = 0.0

    def __post_init__(self) -> None:
        for name in ("enter_bad_pct", "leave_bad_pct", "loss_in_bad_pct", "loss_in_good_pct"):
            value = getattr(self, name)
            if not 0.0 <= value <= 100.0:
                raise ValueError(f"GilbertElliott.{name} must be in [0, 100], got {value}")
        if self.leave_bad_pct == 0.0 and self.enter_bad_pct > 0.0:
            raise ValueError(
                "GilbertElliott.leave_bad_pct is 0: once bad, the link would stay bad forever"
            )

    @property
    def mean_loss_pct(self) -> float:
        """The stationary loss rate in percent (useful for choosing parameters)."""
        total = self.enter_bad_pct + self.leave_bad_pct
        pi_bad = 0.0 if total == 0.0 else self.enter_bad_pct / total
        return pi_bad * self.loss_in_bad_pct + (1.0 - pi_bad) * self.loss_in_good_pct


class Impairment(msgspec.Struct, frozen=True, kw_only=True):
    """What one direction of the link does to packets.  ``Impairment()`` is a clean wire.

    Units follow ``tc netem``: milliseconds, percent, kbit/s.  The struct is frozen and
    msgspec-encodable because it crosses the control channel to the relay process.
    """

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_pct: float = 0.0
    bursts: GilbertElliott | None = None
    rate_kbit: float | None = None
    limit: int = 1000
    reorder: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.delay_ms <= 60_000.0:
            raise ValueError(f"delay_ms must be in [0, 60000], got {self.delay_ms}")
        if not 0.0 <= self.jitter_ms <= 60_000.0:
            raise ValueError(f"jitter_ms must be in [0, 60000], got {self.jitter_ms}")
        if not 0.0 <= self.loss_pct <= 100.0:
            raise ValueError(f"loss_pct must be in [0, 100], got {self.loss_pct}")
        if self.bursts is not None and self.loss_pct != 0.0:
            raise ValueError("give either loss_pct (independent loss) or bursts, not both")
        if self.rate_kbit is not None and self.rate_kbit <= 0.0:
            raise ValueError(f"rate_kbit must be positive or None, got {self.rate_kbit}")
        if self.limit < 1:
            raise ValueError(f"limit must be at least 1 packet, got {self.limit}")

    @property
    def is_clean(self) -> bool:
        """True when this direction neither delays, drops nor shapes."""
        return self == Impairment()


def split_direction(impairment: Impairment, direction: Direction) -> tuple[Impairment, Impairment]:
    """Return ``(a_to_b, b_to_a)`` for an impairment applied to ``direction``.

    The direction not named gets a clean wire.  ``"a_to_b"`` alone reproduces the thesis's
    set-up, where the ``tc filter ... match ip sport`` rule impaired one direction only.
    """
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    clean = Impairment()
    a_to_b = impairment if direction in ("both", "a_to_b") else clean
    b_to_a = impairment if direction in ("both", "b_to_a") else clean
    return a_to_b, b_to_a


def _rng(seed: int, path: str, stream: str) -> random.Random:
    """A deterministic RNG per (seed, direction, purpose); str seeds are hashed stably."""
    return random.Random(f"rlbridge.netem:{seed}:{path}:{stream}")


class PathModel:
    """One direction of the link: admits packets and says when each may leave.

    Not thread-safe; the relay calls it from its single loop.  ``name`` (``"a_to_b"`` or
    ``"b_to_a"``) is part of the RNG seed so the two directions are independent.
    """

    def __init__(self, impairment: Impairment, *, seed: int, name: str) -> None:
        self._impairment = impairment
        self._loss_rng = _rng(seed, name, "loss")
        self._jitter_rng = _rng(seed, name, "jitter")
        self._bad_state = False
        self._busy_until = float("-inf")
        self._last_release = float("-inf")
        self._in_flight: list[float] = []

    @property
    def impairment(self) -> Impairment:
        """The impairment currently applied to newly admitted packets."""
        return self._impairment

    def reconfigure(self, impairment: Impairment) -> None:
        """Apply ``impairment`` to packets admitted from now on.

        Packets already in flight keep their release times; without ``reorder`` a shorter
        new delay therefore queues behind them, as on a real path.  The RNG streams carry
        on (a run stays reproducible) and the Gilbert-Elliott chain restarts in "good".
        """
        self._impairment = impairment
        self._bad_state = False

    def in_flight(self, now: float) -> int:
        """Packets admitted but not yet due at ``now``."""
        self._expire(now)
        return len(self._in_flight)

    def admit(self, now: float, size: int) -> float | DropReason:
        """Decide the fate of a ``size``-byte packet arriving at ``now``.

        Returns the absolute release time (same clock as ``now``) or a :class:`DropReason`.
        """
        imp = self._impairment
        if self._lost(imp):
            return DropReason.LOSS
        self._expire(now)
        if len(self._in_flight) >= imp.limit:
            return DropReason.QUEUE_FULL
        sent_at = now
        if imp.rate_kbit is not None:
            sent_at = max(now, self._busy_until) + size * 8.0 / (imp.rate_kbit * 1000.0)
            self._busy_until = sent_at
        delay_s = imp.delay_ms / 1000.0
        if imp.jitter_ms > 0.0:
            jitter_s = imp.jitter_ms / 1000.0
            delay_s = max(0.0, delay_s + self._jitter_rng.uniform(-jitter_s, jitter_s))
        release = sent_at + delay_s
        if not imp.reorder:
            release = max(release, self._last_release)
        self._last_release = max(self._last_release, release)
        heapq.heappush(self._in_flight, release)
        return release

    def _lost(self, imp: Impairment) -> bool:
        """One loss decision; always consumes the same number of draws per packet."""
        if imp.bursts is None:
            return imp.loss_pct > 0.0 and self._loss_rng.random() * 100.0 < imp.loss_pct
        ge = imp.bursts
        loss_draw = self._loss_rng.random() * 100.0
        step_draw = self._loss_rng.random() * 100.0
        if self._bad_state:
            lost = loss_draw < ge.loss_in_bad_pct
            if step_draw < ge.leave_bad_pct:
                self._bad_state = False
        else:
            lost = loss_draw < ge.loss_in_good_pct
            if step_draw < ge.enter_bad_pct:
                self._bad_state = True
        return lost

    def _expire(self, now: float) -> None:
        while self._in_flight and self._in_flight[0] <= now:
            heapq.heappop(self._in_flight)
