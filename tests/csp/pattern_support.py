"""Bounded waits and readers shared by the CSP tests (the coupling patterns, both layouts;
the channel and doorbell tests wait with :func:`wait_until`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge.csp.bridge import Bridge
from rlbridge.csp.bridge_channels import IncomingChannel

F64 = "std_msgs/msg/Float64"
WAIT = 10.0  # generous bound for anything that should take milliseconds


def wait_until(predicate: Callable[[], bool], what: str, timeout: float = WAIT) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


def publish_until(peer: Bridge, topic: str, value: float, seen: Callable[[], bool]) -> None:
    """Publish ``value`` every 10 ms until the loop has seen it (UDP may drop one)."""
    out = peer.publish(topic, F64, transport="udp")
    deadline = time.monotonic() + WAIT
    while not seen():
        if time.monotonic() > deadline:
            pytest.fail(f"the loop never saw {value} on {topic}")
        out.write(value)
        time.sleep(0.01)


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
