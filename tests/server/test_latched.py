"""Latched topics on the in-process bus: the value a topic holds when a channel binds reaches
the subscriber on either transport, field-bound and whole-message (docs/protocol.md 6.4,
``durability``). The same against real rclpy: tests/adapters/test_ros2_reach_e2e.py."""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any

import pytest

from rlbridge import Bridge, QoS
from rlbridge.wire import Heartbeat, TopicAck, TopicClose, TopicConnect, Value


def _published(bridge: Bridge, topic: str) -> bool:
    channels = bridge.server_stats()["session"]["channels"].values()
    return any(c["topic"] == topic and c["values_in"] > 0 for c in channels)


@pytest.mark.parametrize("publish_via", ["tcp", "udp"])
@pytest.mark.parametrize("transport", ["tcp", "udp"])
@pytest.mark.parametrize("field", ["data", None])
def test_a_late_subscriber_gets_the_latched_value(
        bridge: Callable[..., Bridge], wait_until: Callable[..., Any], field: str | None,
        transport: Any, publish_via: Any) -> None:
    publisher = bridge()
    out = publisher.publish("/latched", "std_msgs/msg/Float64", transport=publish_via,
                            qos=QoS(durability="transient_local"))
    out.write(4.5)
    wait_until(lambda: _published(publisher, "/latched"), what="the value published")
    late = bridge()
    ch = late.subscribe("/latched", "std_msgs/msg/Float64", field, transport=transport,
                        qos=QoS(durability="transient_local"), blocking=True)
    assert ch.read(timeout=10) == (4.5 if field else {"data": 4.5})


def test_a_volatile_subscriber_gets_no_history(
        bridge: Callable[..., Bridge], wait_until: Callable[..., Any]) -> None:
    """The control: without ``transient_local`` the latched value is not replayed."""
    publisher = bridge()
    out = publisher.publish("/latched", "std_msgs/msg/Float64",
                            qos=QoS(durability="transient_local"))
    out.write(4.5)
    wait_until(lambda: _published(publisher, "/latched"), what="the value published")
    ch = bridge().subscribe("/latched", "std_msgs/msg/Float64", transport="udp", blocking=True)
    with pytest.raises(TimeoutError):
        ch.read(timeout=0.5)
    out.write(5.5)
    assert ch.read(timeout=10) == 5.5


def test_values_of_a_udp_channel_bound_before_the_address_is_known_wait_for_it(
        bridge: Callable[..., Bridge], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    """A TCP session's UDP channel binds before its first datagram: the latched value waits
    for the address instead of being dropped (docs/protocol.md 8.3)."""
    publisher = bridge()
    out = publisher.publish("/latched", "std_msgs/msg/Float64",
                            qos=QoS(durability="transient_local"))
    out.write(4.5)
    wait_until(lambda: _published(publisher, "/latched"), what="the value published")
    tcp = raw_tcp()
    ack = tcp.hello()
    tcp.send(TopicConnect(1, "subscribe", "/latched", "std_msgs/msg/Float64", "data", "udp",
                          durability="transient_local"))
    tcp.expect(TopicAck)
    stats = tcp.stats()["session"]["channels"]["1"]
    assert (stats["values_out"], stats["dropped"]) == (1, 0)  # sent into the wait
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.connect(("127.0.0.1", tcp.sock.getpeername()[1]))
        udp.settimeout(10)
        udp.send(tcp.codec.encode_datagram(Heartbeat(1), ack.token))
        while True:
            _flags, token, packet = tcp.codec.decode_datagram(udp.recv(1 << 16))
            if not isinstance(packet, Heartbeat):
                break
    assert token == ack.token
    assert isinstance(packet, Value)
    assert (packet.channel, packet.seq, packet.value) == (1, 0, 4.5)


def test_values_still_waiting_when_the_channel_closes_are_counted_dropped(
        bridge: Callable[..., Bridge], raw_tcp: Callable[..., Any],
        wait_until: Callable[..., Any]) -> None:
    tcp = raw_tcp()
    tcp.hello()
    tcp.send(TopicConnect(1, "subscribe", "/waiting", "std_msgs/msg/Float64", "data", "udp"))
    tcp.expect(TopicAck)
    publisher = bridge()
    out = publisher.publish("/waiting", "std_msgs/msg/Float64", transport="tcp")
    for value in (1.0, 2.0, 3.0):
        out.write(value)
    wait_until(lambda: tcp.stats()["session"]["channels"]["1"]["values_out"] == 3,
               what="three values waiting for the UDP address")
    tcp.send(TopicClose(1))
    session = tcp.stats()["session"]
    assert "1" not in session["channels"]
    assert session["dropped"] == 3  # never sent: counted, not silently lost
