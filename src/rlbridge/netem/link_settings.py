"""What an :class:`~rlbridge.netem.link.EmulatedLink` is asked for, checked before it builds.

Every argument is validated in the constructor, before a namespace exists, so a bad setting
costs nothing to undo; the same helpers turn ``tc netem``-style arguments into the pair of
per-direction impairments the relay takes, and that pair into the label reports print.
"""

from __future__ import annotations

import ipaddress
from typing import Literal

from rlbridge.netem.impairment import Direction, Impairment, split_direction

Side = Literal["a", "b"]

DEFAULT_NETWORK = "10.203.0.0/30"
"""Addresses that exist only inside the link's two namespaces, so every link can reuse them."""

MAX_LIFETIME_S = 24 * 3600.0


def simple_pair(delay_ms: float, loss_pct: float, jitter_ms: float,
                direction: Direction) -> tuple[Impairment, Impairment]:
    """``(a_to_b, b_to_a)`` for netem's ``delay``/``loss``/``jitter`` on ``direction``."""
    simple = Impairment(
        delay_ms=float(delay_ms), loss_pct=float(loss_pct), jitter_ms=float(jitter_ms)
    )
    return split_direction(simple, direction)


def impairment_pair(
    delay_ms: float, loss_pct: float, jitter_ms: float, direction: Direction,
    a_to_b: Impairment | None, b_to_a: Impairment | None,
) -> tuple[Impairment, Impairment]:
    """The link's two directions from either way of giving them (not both, not half)."""
    if (a_to_b is None) != (b_to_a is None):
        raise ValueError("give both a_to_b and b_to_a, or neither")
    if a_to_b is not None and b_to_a is not None:
        if (delay_ms, loss_pct, jitter_ms, direction) != (0.0, 0.0, 0.0, "both"):
            raise ValueError("give either delay/loss/jitter/direction or a_to_b/b_to_a")
        return a_to_b, b_to_a
    return simple_pair(delay_ms, loss_pct, jitter_ms, direction)


def host_pair(network: str) -> tuple[str, str]:
    """The first two host addresses of ``network``: side a's, then side b's."""
    hosts = ipaddress.IPv4Network(network).hosts()
    try:
        return str(next(hosts)), str(next(hosts))
    except StopIteration:
        raise ValueError(f"network {network} has fewer than two host addresses") from None


def check_bounds(mtu: int, max_lifetime_s: float, relay_rt_priority: int | None) -> None:
    """Refuse an MTU IPv4 cannot carry, an unbounded lifetime, or a priority not in 1..99."""
    if not 68 <= mtu <= 65535:
        raise ValueError(f"mtu must be in [68, 65535], got {mtu}")
    if not 0.0 < max_lifetime_s <= MAX_LIFETIME_S:
        raise ValueError(
            f"max_lifetime_s must be in (0, {MAX_LIFETIME_S}], got {max_lifetime_s}"
        )
    if relay_rt_priority is not None and not 1 <= relay_rt_priority <= 99:
        raise ValueError(f"relay_rt_priority must be in [1, 99], got {relay_rt_priority}")


def describe(impairments: tuple[Impairment, Impairment]) -> str:
    """A short label for reports, e.g. ``netem a_to_b=7.5ms/1% b_to_a=clean``."""
    def one(imp: Impairment) -> str:
        if imp.is_clean:
            return "clean"
        parts = [f"{imp.delay_ms:g}ms"]
        if imp.jitter_ms:
            parts.append(f"+-{imp.jitter_ms:g}ms")
        if imp.loss_pct:
            parts.append(f"{imp.loss_pct:g}%")
        if imp.bursts is not None:
            parts.append(f"GE~{imp.bursts.mean_loss_pct:.2g}%")
        if imp.rate_kbit is not None:
            parts.append(f"{imp.rate_kbit:g}kbit")
        return "/".join(parts)

    return f"netem a_to_b={one(impairments[0])} b_to_a={one(impairments[1])}"


def side_index(side: Side) -> int:
    """0 for side ``"a"``, 1 for ``"b"``; anything else is the caller's mistake."""
    if side == "a":
        return 0
    if side == "b":
        return 1
    raise ValueError(f"side must be 'a' or 'b', got {side!r}")
