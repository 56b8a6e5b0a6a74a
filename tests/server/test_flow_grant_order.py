"""A publisher's credit counts the value that just arrived as held (docs/protocol.md 10.5).

The grant is ``arrived + room``: it is exact only if every arrived value already sits with a
subscriber or in its backlog when the room is read. The single-value fast path
(``Inbound.on_value``) once granted before publishing, one value too many at the edge of the
backlog; this drives a real session to that edge through both paths and compares.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from test_value_path_parity import Told

from rlbridge.adapters.inproc import InProcessBus
from rlbridge.server.bindings import Inbound, Outbound
from rlbridge.server.config import ServerConfig
from rlbridge.server.connect import acknowledge, bind
from rlbridge.server.context import ServerContext
from rlbridge.server.flow import BACKLOG_SOFT
from rlbridge.server.handoff import LoopHandoff
from rlbridge.server.session import Session
from rlbridge.wire import Batch, Credit, PacketCodec, TopicConnect, Value

F64 = "std_msgs/msg/Float64"
WINDOW = 4  # the subscriber's credit: it reads nothing


def _granted(single: bool) -> tuple[int, int]:
    """Feed the publisher values until it has no credit left: (values sent, last limit)."""
    loop = asyncio.new_event_loop()
    bus = InProcessBus()
    try:
        ctx = ServerContext(ServerConfig(port=0), bus, PacketCodec(), loop, LoopHandoff(loop))
        session = Session(ctx, 1, 0x1234, "grant", lambda _s: None)
        wire = Told()  # the client's side of the TCP connection: keeps every packet
        session.attach_tcp(wire, lambda: None)
        sub = bind(session, TopicConnect(2, "subscribe", "/grant", F64, transport="tcp",
                                         buffer_size=WINDOW, flow=True))
        assert isinstance(sub, Outbound)
        acknowledge(session, sub, wire)
        pub = bind(session, TopicConnect(1, "publish", "/grant", F64, transport="tcp",
                                         flow=True))
        assert isinstance(pub, Inbound)
        assert pub.credit is not None
        acknowledge(session, pub, wire)
        limit = pub.credit.granted
        seq = 0
        while seq < limit:  # what a publisher honouring its credit sends
            if single:
                pub.on_value(Value(1, seq, 0, float(seq)))
            else:
                pub.on_batch(Batch(1, seq, [0], [float(seq)]))
            seq += 1
            limit = max([limit] + [p.limit for p in wire.packets
                                   if isinstance(p, Credit) and p.channel == 1])
        return seq, limit
    finally:
        bus.close()
        loop.close()


@pytest.mark.parametrize("single", [True, False], ids=["on_value", "on_batch"])
def test_a_publisher_is_granted_exactly_what_the_subscriber_and_its_backlog_hold(
        single: bool) -> None:
    sent, limit = _granted(single)
    assert limit == sent
    assert sent == WINDOW + BACKLOG_SOFT


def test_one_value_and_a_batch_of_one_are_granted_alike() -> None:
    values: list[Any] = [_granted(True), _granted(False)]
    assert values[0] == values[1]
