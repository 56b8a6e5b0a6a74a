"""The SDK's send path loses no value uncounted (docs/concepts.md, "No silent loss"): a value
too large to send counts in ``health().rejected`` on UDP as on TCP, the counts of two threads
add up."""

from __future__ import annotations

import threading
from collections.abc import Callable

from link_helpers import read_all

from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.csp.bell import SendBell
from rlbridge.wire import MAX_DATAGRAM
from rlbridge.wire.link import LinkState

STRING = "std_msgs/msg/String"
F64 = "std_msgs/msg/Float64"


def test_a_udp_value_too_large_for_a_datagram_is_counted_in_rejected(
        bridge: Callable[..., Bridge]) -> None:
    """A value over the largest datagram cannot go: left out with a warning, as on TCP, and
    counted in ``health().rejected`` (it used to be logged only); the values around it
    arrive."""
    sub, pub = bridge(name="dgram-sub"), bridge(name="dgram-pub")
    inbox = sub.subscribe("/dgram/huge", STRING, transport="udp", buffer_size=64)
    out = pub.publish("/dgram/huge", STRING, transport="udp", through_buffer=True)
    out.write_many(["before", "h" * (MAX_DATAGRAM + 1000), "after"])
    pub.send(wait=True)
    assert read_all(inbox, 2) == ["before", "after"]
    assert out.health().rejected == 1
    assert pub.link_state is LinkState.CONNECTED


def test_the_servers_refusals_and_the_send_threads_leftovers_both_count() -> None:
    """``refused`` (receive thread) and ``left_out`` (send thread) keep one counter each, so
    two threads counting at once lose no update; ``health().rejected`` is their sum, with
    what ``write`` refused."""
    ch = OutgoingChannel(1, "/both", F64, "data", transport="tcp", immediate=False,
                         buffer_size=4, doorbell=SendBell())
    rounds = 20_000
    start = threading.Barrier(2)

    def count(step: Callable[[int], None]) -> None:
        start.wait()
        for _ in range(rounds):
            step(1)

    threads = [threading.Thread(target=count, args=(step,)) for step in (ch.refused,
                                                                          ch.left_out)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not any(t.is_alive() for t in threads)
    assert ch.health().rejected == 2 * rounds
