"""Loss reports and credit at the protocol level (a raw TCP client, no SDK in between)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rlbridge import ErrorCode
from rlbridge.wire import (
    Batch,
    ChannelLoss,
    Credit,
    Error,
    LossReport,
    TopicAck,
    TopicConnect,
    Value,
)

F64 = "std_msgs/msg/Float64"


def test_reports_only_when_asked_and_the_last_counts_twice(raw_tcp: Callable[..., Any]) -> None:
    c = raw_tcp()
    c.hello()
    c.send(TopicConnect(1, "publish", "/r", F64, loss_report=True),
           TopicConnect(2, "publish", "/q", F64))  # no reports for this one
    assert c.expect(TopicAck).channel == 1
    assert c.expect(TopicAck).channel == 2
    c.send(Value(1, 0, 0, 1.0), Value(1, 5, 0, 2.0), Value(2, 0, 0, 1.0), Value(2, 9, 0, 1.0))
    first = c.expect(LossReport)
    assert first.channels == [ChannelLoss(1, received=2, lost=4, next_seq=6, refused=0)]
    again = c.expect(LossReport)  # nothing moved: sent once more
    assert again == first


def test_credit_for_a_channel_without_flow_control_is_an_error(
        raw_tcp: Callable[..., Any]) -> None:
    c = raw_tcp()
    c.hello()
    c.send(TopicConnect(3, "subscribe", "/c", F64))
    c.expect(TopicAck)
    c.send(Credit(3, 10))
    err = c.expect(Error)
    assert err.code == ErrorCode.UNKNOWN_CHANNEL
    assert "not a flow-controlled subscription" in err.reason


def test_a_flow_controlled_publisher_gets_its_first_credit_in_the_ack(
        raw_tcp: Callable[..., Any]) -> None:
    sub, pub = raw_tcp(), raw_tcp()
    sub.hello("sub")
    pub.hello("pub")
    sub.send(TopicConnect(1, "subscribe", "/fc", F64, buffer_size=2, flow=True))
    sub.expect(TopicAck)
    pub.send(TopicConnect(1, "publish", "/fc", F64, flow=True))
    ack = pub.expect(TopicAck)
    assert ack.credit is not None
    assert ack.credit > 0
    pub.send(Batch(1, 0, [0] * 5, [float(i) for i in range(5)]))
    got = sub.expect(Batch)  # the subscriber's credit: 2 values, together
    assert got.values == [0.0, 1.0]
    sub.send(Credit(1, 5))  # consumed them: three more may come
    assert sub.expect(Batch).values == [2.0, 3.0, 4.0]
