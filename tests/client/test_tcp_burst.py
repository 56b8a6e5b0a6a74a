"""A burst of large values over TCP against a live server: the SDK cuts it into frames the
server accepts (its ``max_packet``), so the session and its other channels stay up."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.wire.link import LinkState

STRING = "std_msgs/msg/String"
F64 = "std_msgs/msg/Float64"


def read_all(ch: Any, count: int, wait_until: Callable[..., Any]) -> list[Any]:
    got: list[Any] = []

    def more() -> bool:
        got.extend(ch.read_many())
        return len(got) >= count

    wait_until(more, what=f"{count} values")
    return got


def test_a_burst_over_max_packet_arrives_and_the_session_stays_up(
        bridge: Callable[..., Bridge], wait_until: Callable[..., Any]) -> None:
    """2,000 values of 1 KB written at once on a flow-less channel: about 2 MB, which was one
    frame (the server refused it and ended the session); every value arrives, then values
    on another channel of the same session."""
    sub, pub = bridge(name="burst-sub"), bridge(name="burst-pub")
    inbox = sub.subscribe("/burst/big", STRING, transport="tcp", buffer_size=4096)
    after_in = sub.subscribe("/burst/after", F64, transport="tcp", buffer_size=64)
    big = pub.publish("/burst/big", STRING, transport="tcp", through_buffer=True,
                      buffer_size=4096)
    after = pub.publish("/burst/after", F64, transport="tcp")
    session = pub.session_id
    values = [f"{i:04d}" + "v" * 1020 for i in range(2000)]
    big.write_many(values)
    pub.send()
    assert read_all(inbox, 2000, wait_until) == values
    for v in (1.0, 2.0, 3.0):
        after.write(v)
    assert read_all(after_in, 3, wait_until) == [1.0, 2.0, 3.0]
    assert pub.link_state is LinkState.CONNECTED
    assert pub.session_id == session
    assert big.health().rejected == 0


def test_a_value_alone_over_max_packet_is_left_out_and_counted(
        make_server: Callable[..., ServerThread], wait_until: Callable[..., Any]) -> None:
    """A value whose frame alone is over the server's limit cannot go: it is not sent (the
    session would end), counted in ``health().rejected``; the values around it arrive."""
    server = make_server(max_packet=4096)
    sub = Bridge.connect("127.0.0.1", server.port, name="huge-sub", timeout=20)
    pub = Bridge.connect("127.0.0.1", server.port, name="huge-pub", timeout=20)
    try:
        inbox = sub.subscribe("/huge", STRING, transport="tcp", buffer_size=64)
        out = pub.publish("/huge", STRING, transport="tcp", through_buffer=True)
        session = pub.session_id
        out.write_many(["before", "h" * 10_000, "after"])
        pub.send()
        assert read_all(inbox, 2, wait_until) == ["before", "after"]
        wait_until(lambda: out.health().rejected == 1, what="the huge value counted")
        out.write("later")
        pub.send()
        assert read_all(inbox, 1, wait_until) == ["later"]
        assert pub.link_state is LinkState.CONNECTED
        assert pub.session_id == session
    finally:
        pub.close()
        sub.close()
