"""The server's credit bookkeeping (server/flow.py) without sockets: backlog, credit, grants."""

from __future__ import annotations

import asyncio

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


class _CountingFlow(TopicFlow):
    """A topic whose ``room()`` counts its calls: the per-value work the credit does."""

    def __init__(self) -> None:
        super().__init__()
        self.looks = 0

    def room(self) -> int:
        self.looks += 1
        return super().room()


def test_arrivals_look_at_the_room_only_where_a_grant_can_be_due() -> None:
    flow = _CountingFlow()
    sent: list[Credit] = []
    inbound = InboundCredit(5, flow, sent.append)
    assert inbound.first(0) == CREDIT_CHUNK
    assert inbound.check_at == CREDIT_CHUNK // 4  # a quarter chunk on: the next grant
    flow.looks = 0
    for next_seq in range(1, CREDIT_CHUNK // 4):
        inbound.grant(next_seq)
    assert flow.looks == 0  # no grant could be due: one comparison each
    assert sent == []
    inbound.grant(CREDIT_CHUNK // 4)
    assert flow.looks == 1
    assert sent == [Credit(5, CREDIT_CHUNK // 4 + CREDIT_CHUNK)]
    assert inbound.check_at == CREDIT_CHUNK // 2


def test_a_publisher_out_of_credit_is_granted_once_room_appears() -> None:
    flow = TopicFlow()
    sub = OutboundCredit(window=0, flow=flow)
    flow.outbound.add(sub)
    sent: list[Credit] = []
    inbound = InboundCredit(5, flow, sent.append)
    arrived = [0]
    flow.inbound[inbound] = lambda: arrived[0]
    inbound.first(0)
    sub.queue(0, [0] * BACKLOG_SOFT)  # the subscriber reads nothing: no room
    arrived[0] = CREDIT_CHUNK  # the publisher used all its credit
    inbound.grant(arrived[0])
    assert sent == []  # it waits
    assert inbound.check_at == CREDIT_CHUNK  # and is looked at on the next arrival
    sub.on_credit(1)
    sub.take(0, 1)  # one value drained (no loop running: the topic re-grants at once)
    assert sent == [Credit(5, CREDIT_CHUNK + 1)]


def test_drains_of_one_loop_iteration_re_grant_once_at_its_end() -> None:
    async def main() -> tuple[list[Credit], list[Credit]]:
        flow = TopicFlow()
        sub = OutboundCredit(window=10**6, flow=flow)
        flow.outbound.add(sub)
        sent: list[Credit] = []
        inbound = InboundCredit(5, flow, sent.append)
        arrived = [0]
        flow.inbound[inbound] = lambda: arrived[0]
        inbound.first(0)
        for _ in range(BACKLOG_SOFT // 1024):
            sub.queue(0, [0] * 1024)  # the subscriber's backlog full: no room
        arrived[0] = CREDIT_CHUNK
        inbound.grant(arrived[0])
        assert sent == []
        for i in range(BACKLOG_SOFT // 1024):  # it drains, one batch at a time
            sub.take(i * 1024, 1024)
        before = list(sent)  # nothing yet: the re-grant waits for the iteration's end
        await asyncio.sleep(0)
        return before, sent

    before, sent = asyncio.run(main())
    assert before == []
    assert sent == [Credit(5, 2 * CREDIT_CHUNK)]  # one credit for every drain together


def test_values_with_nothing_waiting_pass_the_backlog_within_credit_and_socket() -> None:
    queued = [0]
    out = OutboundCredit(window=4, flow=TopicFlow(), queued=lambda: queued[0], max_queued=50)
    assert out.passes(0, 1)
    assert out.passes(3, 1)
    assert not out.passes(4, 1)  # beyond the client's credit: backlog
    queued[0] = 51
    assert not out.passes(0, 1)  # the socket is full: backlog
    queued[0] = 0
    out.queue(1, [1])
    assert not out.passes(1, 1)  # something waits: behind it, in order
