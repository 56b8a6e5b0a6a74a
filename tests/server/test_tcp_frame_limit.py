"""Server -> client over TCP: no frame over the client's limit (the reference client's
``FrameDecoder`` ends the session on one), even when the server batches a backlog of large
values; a value alone over it is not sent, and the session goes on."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire import Batch, Credit, TopicAck, TopicConnect, Value

STRING = "std_msgs/msg/String"


def values_of(raw: Any, count: int) -> list[tuple[int, str]]:
    """(seq, value) of the next ``count`` values the raw client reads (its decoder has the
    reference limit: a frame over it fails the test)."""
    got: list[tuple[int, str]] = []
    while len(got) < count:
        packet = raw.recv()
        if isinstance(packet, Value):
            got.append((packet.seq, packet.value))
        elif isinstance(packet, Batch):
            got.extend((packet.first_seq + i, v) for i, v in enumerate(packet.values))
    return got


@pytest.mark.parametrize("max_batch", [4096, 400])
def test_a_credited_backlog_of_large_values_comes_in_frames_the_client_reads(
        max_batch: int, make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    """A flow-controlled subscriber with credit for one value lets 2,000 values of 1 KB wait
    in the server's backlog; one ``Credit`` for all of them makes the server send them as a
    ``Batch`` of 2 MB, which was one frame (the client ended the session). With
    ``max_batch`` 400 the batches fit, and it is the corked frames that pass 1 MiB (handed
    to the transport early)."""
    server = make_server(max_batch=max_batch)
    sub = raw_tcp(server.port)
    sub.hello()
    sub.send(TopicConnect(1, "subscribe", "/srv/burst", STRING, transport="tcp",
                          buffer_size=1, flow=True))
    assert isinstance(sub.expect(TopicAck), TopicAck)
    pub = Bridge.connect("127.0.0.1", server.port, name="srv-burst-pub", timeout=20)
    try:
        burst_then_one_more(pub, sub, wait_until)
    finally:
        pub.close()


def burst_then_one_more(pub: Bridge, sub: Any, wait_until: Callable[..., Any]) -> None:
    """2,000 values of 1 KB into the credited subscriber's backlog, all credited at once,
    then one more value: each arrives once, in order (the raw client's decoder has the
    reference limit, so a frame over it fails the test)."""
    out = pub.publish("/srv/burst", STRING, transport="tcp", through_buffer=True,
                      buffer_size=4096)
    values = [f"{i:04d}" + "s" * 1020 for i in range(2000)]
    out.write_many(values)
    pub.send()
    assert values_of(sub, 1) == [(0, values[0])]  # the one value the first credit allows
    # The rest wait in the backlog until the server has them all (its stats say so).
    wait_until(lambda: sub.stats()["session"]["channels"]["1"]["backlog"] == 1999,
               what="the backlog of 1,999 values")
    sub.send(Credit(1, 2000))
    assert values_of(sub, 1999) == list(enumerate(values))[1:]
    # The session is still up: a value after the burst arrives too.
    out.write("after")
    pub.send()
    sub.send(Credit(1, 2001))
    assert values_of(sub, 1) == [(2000, "after")]


def test_a_value_alone_over_the_clients_limit_is_not_sent_and_is_counted(
        make_server: Callable[..., ServerThread], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    """A server taking frames of 2 MiB passes on a value of 1.5 MB: a client would end its
    session on that frame, so the server leaves it out (``dropped``) and goes on."""
    server = make_server(max_packet=2 << 20)
    sub = raw_tcp(server.port)
    sub.hello()
    sub.send(TopicConnect(1, "subscribe", "/srv/huge", STRING, transport="tcp"))
    sub.expect(TopicAck)
    pub = Bridge.connect("127.0.0.1", server.port, name="srv-huge-pub", timeout=20)
    try:
        out = pub.publish("/srv/huge", STRING, transport="tcp", through_buffer=True)
        for value in ("before", "h" * 1_500_000, "after"):  # one round, one Value each
            out.write(value)
            pub.send(wait=True)
        assert values_of(sub, 2) == [(0, "before"), (2, "after")]
        wait_until(lambda: sub.stats()["session"]["channels"]["1"]["dropped"] == 1,
                   what="the huge value counted as dropped")
    finally:
        pub.close()
