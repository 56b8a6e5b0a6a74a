"""The SDK's send path loses no value uncounted (docs/concepts.md, "No silent loss"): a value
too large to send counts in ``health().rejected`` on UDP as on TCP, the counts of two threads
add up, and a reconnect to a server with other limits batches by the new ones."""

from __future__ import annotations

import threading
from collections.abc import Callable

from link_helpers import read_all

from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.outgoing import OutgoingChannel
from rlbridge.client.session.reconnect import Backoff
from rlbridge.csp.bell import SendBell
from rlbridge.server import ServerConfig, ServerThread
from rlbridge.wire import MAX_DATAGRAM
from rlbridge.wire.link import LinkState
from waiting import wait_until

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


def test_max_batch_follows_a_reconnect(free_port: Callable[[], int]) -> None:
    """The send round reads the server's ``max_batch`` from the current session's ack (as its
    ``max_packet``): after a reconnect to a server of ``max_batch`` 3, ten values waiting in
    one channel leave as four frames, not one."""
    port = free_port()

    def server(max_batch: int) -> ServerThread:
        return ServerThread(ServerConfig(port=port, heartbeat_ms=100, timeout_ms=5000,
                                         max_batch=max_batch)).start()

    first = server(4096)
    second: ServerThread | None = None
    pub = Bridge.connect("127.0.0.1", port, name="batch-pub", timeout=20,
                         reconnect=Backoff(initial=0.02, max_delay=0.2))
    try:
        out = pub.publish("/batch", F64, transport="tcp", through_buffer=True, buffer_size=64)
        sender = pub._sender
        sent = sender.packets_sent
        out.write_many([float(i) for i in range(10)])
        pub.send(wait=True)
        assert sender.packets_sent - sent == 1  # the first server's limit: one Batch
        first.stop()
        second = server(3)
        with Bridge.connect("127.0.0.1", port, name="batch-sub", timeout=20) as sub:
            inbox = sub.subscribe("/batch", F64, transport="tcp", buffer_size=64)
            wait_until(lambda: pub.reconnects >= 1 and pub.link_state is LinkState.CONNECTED,
                       what="the publisher on the second server")
            sent = sender.packets_sent
            out.write_many([float(i) for i in range(10)])
            pub.send(wait=True)
            assert read_all(inbox, 10) == [float(i) for i in range(10)]
            assert sender.packets_sent - sent == 4  # batches of 3, 3, 3, 1
    finally:
        pub.close()
        first.stop()
        if second is not None:
            second.stop()
