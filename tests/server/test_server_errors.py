"""Every refusal names the problem, and the session stays usable afterwards."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ErrorCode
from rlbridge.wire import Batch, Error, Stats, TopicAck, TopicClose, TopicConnect, TopicError, Value

F64 = "std_msgs/msg/Float64"
TWIST = "geometry_msgs/msg/Twist"


def assert_usable(client: Any, channel: int = 900) -> None:
    """The session still binds channels and answers requests."""
    client.send(TopicConnect(channel, "publish", f"/usable/c{channel}", F64, transport="tcp"))
    assert client.expect(TopicAck).channel == channel
    client.send(Value(channel, 0, 0, 1.0))
    client.send(Stats())
    body = client.expect(Stats).body
    assert body["session"]["state"] == "connected"
    assert body["session"]["channels"][str(channel)]["values_in"] == 1


BINDING_ERRORS = [
    pytest.param(TopicConnect(1, "subscribe", "/t/a", "std_msgs/msg/Nope"),
                 ErrorCode.UNKNOWN_TYPE, ["unknown message type 'std_msgs/msg/Nope'",
                                          "std_msgs/msg/Float64"], id="unknown-type"),
    pytest.param(TopicConnect(1, "publish", "/t/a", "Float64"),
                 ErrorCode.UNKNOWN_TYPE, ["'Float64' is not a message type name",
                                          "package/msg/Type"], id="bad-type-name"),
    pytest.param(TopicConnect(1, "publish", "/t/a", F64, "datum"),
                 ErrorCode.NO_SUCH_FIELD, ["has no field 'datum'", "fields here: data"],
                 id="no-such-field"),
    pytest.param(TopicConnect(1, "subscribe", "/t/a", TWIST, "linear.w"),
                 ErrorCode.NO_SUCH_FIELD, ["has no field 'linear.w'", "x, y, z"],
                 id="no-such-nested-field"),
    pytest.param(TopicConnect(1, "subscribe", "/t/a", TWIST, "linear.x.y"),
                 ErrorCode.NO_SUCH_FIELD, ["'y' is not in a message"], id="field-of-a-scalar"),
    pytest.param(TopicConnect(1, "subscribe", "/t/a", TWIST, "linear..x"),
                 ErrorCode.NO_SUCH_FIELD, ["empty segment"], id="empty-field-segment"),
    pytest.param(TopicConnect(1, "publish", "no_slash", F64),
                 ErrorCode.BAD_TOPIC, ["'no_slash' is not a valid topic name"], id="no-slash"),
    pytest.param(TopicConnect(1, "publish", "/has space", F64),
                 ErrorCode.BAD_TOPIC, ["'/has space' is not a valid topic name"], id="space"),
    pytest.param(TopicConnect(1, "publish", "/2fast", F64),
                 ErrorCode.BAD_TOPIC, ["digit-leading"], id="digit-leading"),
    pytest.param(TopicConnect(1, "publish", "/trailing/", F64),
                 ErrorCode.BAD_TOPIC, ["not a valid topic name"], id="trailing-slash"),
]


@pytest.mark.parametrize(("request_", "code", "phrases"), BINDING_ERRORS)
def test_refused_binding(raw_tcp: Callable[..., Any], request_: TopicConnect, code: ErrorCode,
                         phrases: list[str]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(request_)
    err = client.expect(TopicError)
    assert err.channel == request_.channel
    assert err.code == code
    for phrase in phrases:
        assert phrase in err.reason
    # The refused channel id is free again.
    client.send(TopicConnect(1, "publish", "/t/fine", F64, transport="tcp"))
    assert client.expect(TopicAck).channel == 1
    assert_usable(client)


def test_topic_bound_to_another_type(raw_tcp: Callable[..., Any]) -> None:
    owner = raw_tcp()
    owner.hello()
    owner.send(TopicConnect(1, "publish", "/typed", F64, transport="tcp"))
    owner.expect(TopicAck)
    other = raw_tcp()
    other.hello()
    other.send(TopicConnect(5, "subscribe", "/typed", "std_msgs/msg/Int8", transport="tcp"))
    err = other.expect(TopicError)
    assert err.code == ErrorCode.TYPE_CLASH
    assert err.channel == 5
    assert err.reason == "topic '/typed' has type std_msgs/msg/Float64, not std_msgs/msg/Int8"
    # ROS 1 spelling of the same type is the same type.
    other.send(TopicConnect(6, "subscribe", "/typed", "std_msgs/Float64", transport="tcp"))
    assert other.expect(TopicAck).msg_type == F64
    assert_usable(other)


def test_channel_in_use(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    first = TopicConnect(3, "publish", "/in/use", F64, transport="tcp")
    client.send(first)
    client.expect(TopicAck)
    client.send(first)  # the very same request again (a retransmission): answered again
    assert client.expect(TopicAck).channel == 3
    client.send(TopicConnect(3, "publish", "/in/other", F64, transport="tcp"))
    err = client.expect(TopicError)
    assert err.code == ErrorCode.CHANNEL_IN_USE
    assert "channel 3 is already connected" in err.reason
    assert_usable(client)


def test_channel_limit(make_server: Callable[..., Any], raw_tcp: Callable[..., Any]) -> None:
    srv = make_server(max_channels=2)
    client = raw_tcp(srv.port)
    client.hello()
    for ch in (1, 2):
        client.send(TopicConnect(ch, "publish", f"/lim/c{ch}", F64, transport="tcp"))
        client.expect(TopicAck)
    client.send(TopicConnect(3, "publish", "/lim/c3", F64, transport="tcp"))
    err = client.expect(TopicError)
    assert err.code == ErrorCode.LIMIT
    assert "2 channels" in err.reason
    client.send(TopicClose(2))
    client.send(TopicConnect(3, "publish", "/lim/c3", F64, transport="tcp"))
    assert client.expect(TopicAck).channel == 3


VALUE_ERRORS = [
    pytest.param(F64, "data", "not a number", "Expected `float`, got `str`", id="str-for-float"),
    pytest.param(F64, "data", [1.0], "Expected `float`, got `array`", id="list-for-float"),
    pytest.param("std_msgs/msg/Int8", "data", 128, "Expected `int` <= 127", id="int8-too-big"),
    pytest.param("std_msgs/msg/Int8", "data", -129, "Expected `int` >= -128", id="int8-too-small"),
    pytest.param("std_msgs/msg/Int8", "data", 1.5, "Expected `int`, got `float`",
                 id="float-for-int"),
    pytest.param("std_msgs/msg/UInt8", "data", -1, "Expected `int` >= 0", id="negative-uint"),
    pytest.param("std_msgs/msg/Bool", "data", 1, "Expected `bool`, got `int`", id="int-for-bool"),
    pytest.param("std_msgs/msg/String", "data", 5, "Expected `str`, got `int`", id="int-for-str"),
    pytest.param(TWIST, None, {"linear": {"x": "fast"}}, "Expected `float`, got `str`",
                 id="bad-nested-field"),
    pytest.param(TWIST, None, {"linear": {"w": 1.0}}, "unknown field `w`", id="unknown-field"),
    pytest.param(TWIST, None, 3.0, "Expected `object`, got `float`", id="scalar-for-message"),
]


@pytest.mark.parametrize(("msg_type", "field", "value", "phrase"), VALUE_ERRORS)
def test_value_of_the_wrong_kind(raw_tcp: Callable[..., Any], msg_type: str, field: str | None,
                                 value: Any, phrase: str) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(4, "publish", "/kinds", msg_type, field, transport="tcp"))
    client.expect(TopicAck)
    client.send(Value(4, 0, 0, value))
    err = client.expect(Error)
    assert err.code == ErrorCode.BAD_VALUE
    assert err.channel == 4
    assert f"channel 4 ({msg_type} field {field or '<whole message>'})" in err.reason
    assert phrase in err.reason
    body = client.stats()
    assert body["session"]["channels"]["4"]["bad_values"] == 1
    assert body["session"]["channels"]["4"]["values_in"] == 0
    assert_usable(client)


def test_bad_value_inside_a_batch_names_its_index(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(4, "publish", "/kinds", "std_msgs/msg/Int8", transport="tcp"))
    client.expect(TopicAck)
    client.send(Batch(4, 0, [0, 0, 0], [1, 2, 1000]))
    err = client.expect(Error)
    assert err.code == ErrorCode.BAD_VALUE
    assert "at `$[2]`" in err.reason
    assert_usable(client)


def test_only_the_bad_values_of_a_batch_are_refused(raw_tcp: Callable[..., Any]) -> None:
    """Five values, two bad: the three good ones are published in order, the error counts 2."""
    client = raw_tcp()
    client.hello()
    client.send(TopicConnect(5, "subscribe", "/mixed", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(TopicConnect(4, "publish", "/mixed", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(Batch(4, 0, [0] * 5, [1.0, "abc", 2, None, 3.0]))
    received: list[Any] = []
    error: Error | None = None
    while error is None or len(received) < 3:
        packet = client.recv()
        if isinstance(packet, Error):
            error = packet
        elif isinstance(packet, Value | Batch):
            received.extend([packet.value] if isinstance(packet, Value) else packet.values)
    assert received == [1.0, 2.0, 3.0]
    assert (error.code, error.channel, error.values) == (ErrorCode.BAD_VALUE, 4, 2)
    assert "2 of 5 values refused" in error.reason
    assert "at `$[1]`" in error.reason  # the first bad one, by its index in the batch
    channel = client.stats()["session"]["channels"]["4"]
    assert (channel["values_in"], channel["bad_values"], channel["rejected"]) == (3, 2, 2)
    assert_usable(client)


def test_values_on_unknown_channels(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(Value(42, 0, 0, 1.0))
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.UNKNOWN_CHANNEL, 42)
    assert "channel 42 is not connected" in err.reason

    client.send(TopicConnect(5, "subscribe", "/sub/only", F64, transport="tcp"))
    client.expect(TopicAck)
    client.send(Batch(5, 0, [0], [1.0]))
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.UNKNOWN_CHANNEL, 5)
    assert "is bound for subscribing" in err.reason

    client.send(TopicClose(77))
    err = client.expect(Error)
    assert (err.code, err.channel) == (ErrorCode.UNKNOWN_CHANNEL, 77)

    client.send(TopicClose(5))
    client.send(Value(5, 1, 0, 1.0))
    err = client.expect(Error)
    assert "channel 5 is not connected" in err.reason
    assert_usable(client)
    assert client.stats()["session"]["errors_sent"] == 4


def test_server_only_packets_from_a_client(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello()
    client.send(TopicAck(1, F64, 0.0))
    err = client.expect(Error)
    assert err.code == ErrorCode.UNEXPECTED
    assert "a client may not send TopicAck" in err.reason
    assert_usable(client)
