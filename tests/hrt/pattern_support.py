"""Bounded waits and readers shared by the CSP tests (the coupling patterns, both layouts;
the channel and doorbell tests wait with :func:`wait_until`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.incoming import IncomingChannel
from waiting import WAIT, wait_until

F64 = "std_msgs/msg/Float64"
__all__ = ["F64", "WAIT", "collect", "drain", "publish_until", "wait_until"]


def publish_until(peer: Bridge, topic: str, value: float, seen: Callable[[], bool]) -> None:
    """Publish ``value`` every 10 ms until the loop has seen it (UDP may drop one)."""
    out = peer.publish(topic, F64, transport="udp")
    wait_until(seen, f"the loop to see {value} on {topic}", between=lambda: out.write(value))


def collect(channel: IncomingChannel, count: int) -> list[Any]:
    """Read ``count`` values from a blocking subscription (fails after WAIT seconds)."""
    got: list[Any] = []
    deadline = time.monotonic() + WAIT
    while len(got) < count:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            got.append(channel.read(timeout=left))
        except TimeoutError:
            break
    return got


def drain(channel: IncomingChannel, quiet: float = 0.3) -> list[Any]:
    """Everything that arrives until ``quiet`` seconds pass without a value."""
    got: list[Any] = []
    while True:
        try:
            got.append(channel.read(timeout=quiet))
        except TimeoutError:
            return got
