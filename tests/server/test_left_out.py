"""Server -> client: a value left out of a packet the server otherwise sends (alone too large
for the client: over its frame limit on TCP, over a datagram on UDP) counts in the channel's
``dropped``, what ``rlbridge stats`` shows (docs/concepts.md, "No silent loss"), once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from test_tcp_frame_limit import values_of

from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import TopicAck, TopicConnect

STRING = "std_msgs/msg/String"


def test_a_value_cut_out_of_a_tcp_batch_counts_in_the_channels_dropped(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    """A server taking frames of 2 MiB gets one Batch of three values, the middle one 1.5 MB:
    its Batch to a client is cut, the 1.5 MB value left out (a frame the client would end its
    session on) and counted in the channel's ``dropped`` (it was only in the sink's own
    count, which nothing reports); the other two arrive."""
    server = make_server(max_packet=2 << 20)
    sub = raw_tcp(server.port)
    sub.hello()
    sub.send(TopicConnect(1, "subscribe", "/left/tcp", STRING, transport="tcp"))
    sub.expect(TopicAck)
    with Bridge.connect("127.0.0.1", server.port, name="left-tcp-pub", timeout=20) as pub:
        out = pub.publish("/left/tcp", STRING, transport="tcp", through_buffer=True)
        out.write_many(["before", "h" * 1_500_000, "after"])  # one round: one Batch
        pub.send(wait=True)
        assert values_of(sub, 2) == [(0, "before"), (2, "after")]
        wait_until(lambda: sub.stats()["session"]["channels"]["1"]["dropped"] == 1,
                   what="the left-out value counted as dropped")


def test_a_value_over_a_datagram_in_a_udp_batch_counts_once(
        make_server: Callable[..., ServerThread], wait_until: Callable[..., Any]) -> None:
    """A Batch of three values to a UDP subscriber, the middle one over the server's datagram
    size: the two that fit arrive, and ``dropped`` counts the one left out (the whole Batch
    of three was counted, though two were sent)."""
    server = make_server(udp_payload=1400)
    with Bridge.connect("127.0.0.1", server.port, name="left-udp-sub", timeout=20) as sub, \
            Bridge.connect("127.0.0.1", server.port, name="left-udp-pub", timeout=20) as pub:
        inbox = sub.subscribe("/left/udp", STRING, transport="udp", buffer_size=64)
        out = pub.publish("/left/udp", STRING, transport="tcp", through_buffer=True)
        out.write_many(["before", "h" * 3000, "after"])  # one round: one Batch
        pub.send(wait=True)
        got: list[Any] = []
        wait_until(lambda: got.extend(inbox.read_many()) or len(got) >= 2,
                   what="the two values that fit")
        assert got == ["before", "after"]
        key = str(inbox.channel_id)

        def dropped() -> int:
            return int(sub.server_stats()["session"]["channels"][key]["dropped"])

        wait_until(lambda: dropped() >= 1, what="the value over a datagram counted")
        assert dropped() == 1
