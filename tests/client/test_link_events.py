"""Link events and fail-safes without a network: ordering, repeats, buffers, policies."""

from __future__ import annotations

import threading

import pytest

from rlbridge import LinkLost, WouldBlock
from rlbridge.csp.failsafe import FailSafe, SafeValue, fail_safe
from rlbridge.csp.link_events import LinkEvents
from rlbridge.errors import ChannelClosed
from rlbridge.wire.link import LinkState


def test_events_reach_channels_and_callbacks_in_order_without_repeats() -> None:
    hub = LinkEvents()
    seen: list[LinkState] = []
    hub.add_callback(seen.append)
    ch = hub.channel()
    assert ch.read().state is LinkState.CONNECTED
    hub.emit(LinkState.DEGRADED, "quiet")
    hub.emit(LinkState.DEGRADED, "still quiet")  # not a change: ignored
    hub.emit(LinkState.LOST, "watchdog")
    hub.emit(LinkState.CONNECTED, "reconnected")
    events = ch.read_many()
    assert [(e.state, e.reason) for e in events] == [
        (LinkState.DEGRADED, "quiet"), (LinkState.LOST, "watchdog"),
        (LinkState.CONNECTED, "reconnected")]
    assert [e.at_ns for e in events] == sorted(e.at_ns for e in events)
    assert seen == [LinkState.DEGRADED, LinkState.LOST, LinkState.CONNECTED]
    late = hub.channel()  # a late subscriber starts from the current state
    assert late.read() is events[-1]


def test_link_events_are_a_fifo_each_event_read_once() -> None:
    """Events are not state: a drain loop ends (``try_read`` raises ``WouldBlock``) instead
    of reading the newest event again forever, and ``read`` waits for the next one."""
    hub = LinkEvents()
    ch = hub.channel()
    assert ch.try_read().state is LinkState.CONNECTED
    with pytest.raises(WouldBlock, match="try_read on channel 'link events' would block"):
        ch.try_read()
    assert ch.read_many() == []
    with pytest.raises(TimeoutError):
        ch.read(timeout=0.01)
    drained = []
    hub.emit(LinkState.LOST, "down")
    hub.emit(LinkState.CONNECTED, "up")
    while True:  # the loop the README teaches: bounded by what was emitted
        try:
            drained.append(ch.try_read().reason)
        except WouldBlock:
            break
    assert drained == ["down", "up"]
    waiting = threading.Event()
    got: list[str] = []

    def reader() -> None:
        waiting.set()
        got.append(ch.read(timeout=30).reason)

    thread = threading.Thread(target=reader)
    thread.start()
    waiting.wait(30)
    hub.emit(LinkState.DEGRADED, "quiet")  # wakes the blocked reader (or it finds it first)
    thread.join(30)
    assert got == ["quiet"]


def test_a_slow_event_reader_loses_the_oldest_counted_and_closed_channels_are_dropped() -> None:
    hub = LinkEvents()
    small = hub.channel(buffer_size=2)
    for _ in range(3):
        hub.emit(LinkState.LOST, "down")
        hub.emit(LinkState.CONNECTED, "up")
    assert [e.reason for e in small.read_many()] == ["down", "up"]
    assert small.statistics().overwritten == 5  # the first state and four changes
    small.close()
    hub.emit(LinkState.LOST, "down")  # no write into a closed channel
    hub.close()
    with pytest.raises(ChannelClosed):
        small.read()


def test_fail_safe_policies_follow_the_flag() -> None:
    hub = LinkEvents()
    assert fail_safe("hold", hub) is None
    safe = fail_safe(SafeValue(0.0), hub)
    strict = fail_safe("raise", hub)
    assert isinstance(safe, FailSafe)
    assert isinstance(strict, FailSafe)
    assert not safe.active
    hub.emit(LinkState.LOST, "down")
    assert safe.active
    assert safe.read("ch") == 0.0
    with pytest.raises(LinkLost, match="'ch'"):
        strict.read("ch")
    hub.emit(LinkState.CONNECTED, "up")
    assert not strict.active
    with pytest.raises(ValueError, match="on_lost must be"):
        fail_safe(0.0, hub)  # type: ignore[arg-type]
