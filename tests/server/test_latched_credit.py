"""A latched topic's stored values on a flow-controlled channel: they follow the TopicAck and
use the client's credit like live values (docs/protocol.md 9 and 10.5), on a live server over
loopback. The property: whatever the store, the first credit (``buffer_size``, 0 included: a
client re-binding with a full ring) and the grants, the values on the stream never pass the
limit granted, and every stored value arrives once, in order."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlbridge import Bridge, QoS
from rlbridge.wire import Batch, Credit, Stats, TopicAck, TopicConnect, Value

I64 = "std_msgs/msg/Int64"
_topics = itertools.count()


def _published(bridge: Bridge, topic: str, count: int) -> bool:
    channels = bridge.server_stats()["session"]["channels"].values()
    return any(c["topic"] == topic and c["values_in"] == count for c in channels)


def _values_until_stats(tcp: Any) -> tuple[list[tuple[int, int]], dict[str, Any]]:
    """Ask for the server's counters and read up to the answer: ``(seq, value)`` of every
    value before it. The server handles packets in order and a control frame flushes the
    values corked before it, so whatever it sent before the ``Stats`` request is in here."""
    tcp.send(Stats())
    got: list[tuple[int, int]] = []
    while True:
        packet = tcp.recv()
        if isinstance(packet, Stats):
            return got, packet.body["session"]["channels"]["1"]
        if isinstance(packet, Value):
            got.append((packet.seq, packet.value))
        elif isinstance(packet, Batch):
            got += [(packet.first_seq + i, v) for i, v in enumerate(packet.values)]
        else:
            raise AssertionError(f"unexpected {packet!r}")


@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(published=st.integers(1, 12), depth=st.integers(1, 10), ring=st.integers(0, 8),
       steps=st.lists(st.integers(1, 5), min_size=1, max_size=6))
def test_stored_values_follow_the_ack_within_the_credit(
        bridge: Callable[..., Bridge], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any], published: int, depth: int, ring: int,
        steps: list[int]) -> None:
    topic = f"/latched/credit/t{next(_topics)}"
    publisher = bridge()
    out = publisher.publish(topic, I64, transport="tcp",
                            qos=QoS(durability="transient_local", depth=depth))
    out.write_many(list(range(published)))
    wait_until(lambda: _published(publisher, topic, published), what="the values published")
    stored = list(range(published))[-depth:]

    tcp = raw_tcp()
    tcp.hello()
    tcp.send(TopicConnect(1, "subscribe", topic, I64, "data", "tcp", buffer_size=ring,
                          depth=depth, durability="transient_local", flow=True))
    assert isinstance(tcp.recv(), TopicAck)  # the ack first, then the stored values
    limit = ring
    got, counters = _values_until_stats(tcp)
    assert got == list(enumerate(stored))[:limit]
    assert counters["backlog"] == len(stored) - len(got)
    assert counters["dropped"] == 0
    for step in steps:
        limit += step
        tcp.send(Credit(1, limit))
        more, counters = _values_until_stats(tcp)
        got += more
        assert len(got) <= limit  # never more in flight than granted
        assert got == list(enumerate(stored))[:limit]
    assert counters["backlog"] == len(stored) - len(got)
    publisher.close()
    tcp.close()
