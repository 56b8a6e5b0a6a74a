"""The server's credit bookkeeping (server/flow.py) without sockets: backlog, credit, grants."""

from __future__ import annotations

from rlbridge.server.flow import (
    BACKLOG_HARD,
    BACKLOG_SOFT,
    CREDIT_CHUNK,
    FlowTable,
    InboundCredit,
    OutboundCredit,
    TopicFlow,
    wants_flow,
)
from rlbridge.wire import Credit, TopicConnect


def test_only_tcp_every_value_channels_that_ask_are_flow_controlled() -> None:
    base = TopicConnect(1, "subscribe", "/t", "std_msgs/msg/Int64", flow=True, transport="tcp")
    assert wants_flow(base)
    assert not wants_flow(TopicConnect(1, "subscribe", "/t", "std_msgs/msg/Int64"))
    assert not wants_flow(TopicConnect(1, "subscribe", "/t", "std_msgs/msg/Int64", flow=True,
                                       transport="udp"))
    assert not wants_flow(TopicConnect(1, "subscribe", "/t", "std_msgs/msg/Int64", flow=True,
                                       latest=True))


def test_outbound_sends_within_credit_and_backlogs_the_rest() -> None:
    out = OutboundCredit(window=3, flow=TopicFlow())
    assert out.queue(7, list(range(5))) == 0
    assert out.take(0, 2) == ([7, 7], [0, 1])  # at most two per take
    assert out.take(2, 10) == ([7], [2])
    assert out.take(3, 10) == ([], [])  # no credit left
    assert not out.on_credit(2)  # old news
    assert out.on_credit(4)
    assert out.take(3, 10) == ([7], [3])
    assert out.waiting == 1
    assert out.room() == BACKLOG_SOFT - 1


def test_batches_are_taken_across_their_boundaries_in_order() -> None:
    out = OutboundCredit(window=100, flow=TopicFlow())
    out.queue(1, [0, 1, 2])
    out.queue(2, [3, 4])
    out.queue(3, [5])
    assert out.take(0, 4) == ([1, 1, 1, 2], [0, 1, 2, 3])
    assert out.take(4, 10) == ([2, 3], [4, 5])
    assert out.waiting == 0
    out.queue(4, [6, 7])
    assert out.clear() == 2


def test_a_full_socket_keeps_values_in_the_backlog() -> None:
    queued = [100]
    out = OutboundCredit(window=10, flow=TopicFlow(), queued=lambda: queued[0], max_queued=50)
    out.queue(0, [1, 2])
    assert out.take(0, 10) == ([], [])
    assert out.socket_full
    queued[0] = 0
    assert out.take(0, 10) == ([0, 0], [1, 2])
    assert not out.socket_full


def test_backlog_beyond_the_hard_cap_is_dropped_and_counted() -> None:
    out = OutboundCredit(window=1, flow=TopicFlow())
    assert out.queue(0, [0] * (BACKLOG_HARD + 5)) == 5
    assert out.waiting == BACKLOG_HARD


def test_publishers_get_credit_as_the_slowest_subscriber_makes_room() -> None:
    flow = TopicFlow()
    fast, slow = OutboundCredit(10**6, flow), OutboundCredit(0, flow)
    flow.outbound |= {fast, slow}
    sent: list[Credit] = []
    inbound = InboundCredit(5, flow, sent.append)
    arrived = [0]
    flow.inbound[inbound] = lambda: arrived[0]
    assert inbound.first(0) == CREDIT_CHUNK  # both backlogs empty: a chunk
    slow.queue(0, [0] * BACKLOG_SOFT)  # the slow one's backlog is full
    arrived[0] = CREDIT_CHUNK
    inbound.grant(arrived[0])
    assert sent == []  # no room: no credit, the publisher waits
    slow.on_credit(100)
    slow.take(0, 1000)  # the subscriber read: 100 left the backlog, the flow re-grants
    assert sent == [Credit(5, CREDIT_CHUNK + 100)]


def test_flow_table_forgets_unused_topics() -> None:
    table = FlowTable()
    flow = table.topic("/a")
    assert table.topic("/a") is flow
    table.release("/a")
    assert table.topic("/a") is not flow
