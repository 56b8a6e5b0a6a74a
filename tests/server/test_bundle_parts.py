"""A bundle's parts take the server's fast value path; each must still count as if alone.

The same five values (one good, one for an unknown channel, a duplicate, one of the wrong type,
one after a gap) are sent once as one ``Bundle`` and once as five datagrams; the values
delivered, the errors answered and every counter must be the same both ways.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import ErrorCode
from rlbridge.wire import Bundle, Error, Stats, TopicAck, TopicConnect, Value

F64 = "std_msgs/msg/Float64"


@pytest.mark.parametrize("bundled", [True, False], ids=["bundle", "alone"])
def test_each_part_counts_as_if_it_came_alone(raw_udp: Callable[..., Any], bundled: bool) -> None:
    client = raw_udp()
    client.hello("parts")
    topic = f"/parts/{'bundle' if bundled else 'alone'}"
    client.send(TopicConnect(1001, "subscribe", topic, F64, transport="udp"))
    client.expect(TopicAck)
    client.send(TopicConnect(1, "publish", topic, F64, transport="udp"))
    client.expect(TopicAck)
    now = time.time_ns()
    parts = [Value(1, 0, now, 1.5), Value(7, 0, now, 2.0), Value(1, 0, now, 9.9),
             Value(1, 1, now, "not a float"), Value(1, 3, now, 4.0)]
    if bundled:
        client.send(Bundle(parts))
    else:
        for part in parts:
            client.send(part)
    values: list[float] = []
    errors: list[Error] = []
    while len(values) < 2 or len(errors) < 2:
        packet = client.recv()
        if isinstance(packet, Value):
            assert packet.channel == 1001
            values.append(packet.value)
        else:
            assert isinstance(packet, Error), packet
            errors.append(packet)
    assert values == [1.5, 4.0]
    assert sorted((e.code, e.channel, e.values) for e in errors) == sorted(
        [(int(ErrorCode.UNKNOWN_CHANNEL), 7, 0), (int(ErrorCode.BAD_VALUE), 1, 1)])
    client.send(Stats())
    session = client.expect(Stats).body["session"]
    channel = session["channels"]["1"]
    assert (channel["values_in"], channel["duplicates"], channel["lost"],
            channel["bad_values"]) == (2, 1, 1, 1)
    assert session["channels"]["1001"]["values_out"] == 2
    assert session["dropped"] == 1  # the unknown channel's value
    assert session["packets_in"] == (1 if bundled else 5) + 3  # two topic-connects, Stats
