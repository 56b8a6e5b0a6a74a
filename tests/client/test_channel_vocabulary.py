"""Both directions of a bridge channel speak one vocabulary (docs/api.md has the table).

``write``/``try_write``, ``read``/``try_read``/``read_many``, ``close``, ``with``,
``statistics()``, ``health()``. A verb that cannot mean anything for a direction (reading what
this program publishes) raises ``ChannelMisuseError`` saying why; closing a channel (or
leaving its ``with`` block) unbinds its topic on the server, as ``Bridge.unsubscribe`` does.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from rlbridge import (
    Bridge,
    Channel,
    ChannelClosed,
    ChannelHealth,
    ChannelMisuseError,
    ChannelStatistics,
    IncomingChannel,
    OutgoingChannel,
    RlbridgeError,
)

F64 = "std_msgs/msg/Float64"
WAIT = 10.0
VOCABULARY = ("write", "try_write", "read", "try_read", "read_many", "close", "__enter__",
              "__exit__", "statistics", "health", "name", "closed")


def bound(b: Bridge) -> set[int]:
    """The channel ids the server has bound for this session."""
    return {int(k) for k in b.server_stats()["session"]["channels"]}


def test_both_directions_have_every_verb() -> None:
    for kind in (IncomingChannel, OutgoingChannel):
        missing = [verb for verb in VOCABULARY if not hasattr(kind, verb)]
        assert not missing, f"{kind.__name__} lacks {missing}"


def test_an_outgoing_channel_writes_and_refuses_to_be_read(
        bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    inbox = b.subscribe("/vocab/out", F64, transport="tcp", blocking=True, buffer_size=8)
    with b.publish("/vocab/out", F64, transport="tcp") as out:
        out.try_write(1.5)  # never waits: a full buffer drops its oldest value instead
        out.write(2.5)
        assert [inbox.read(timeout=WAIT), inbox.read(timeout=WAIT)] == [1.5, 2.5]
        for verb, call in (("read", out.read), ("try_read", out.try_read),
                           ("read_many", out.read_many)):
            with pytest.raises(ChannelMisuseError, match=rf"{verb}\(\) on outgoing channel "
                               r"'/vocab/out'.*subscribe to it") as info:
                call()
            assert isinstance(info.value, RlbridgeError)
        assert isinstance(out.statistics(), ChannelStatistics)
        assert isinstance(out.health(), ChannelHealth)
        assert out.name == "/vocab/out out"
        assert out.channel_id in bound(b)
    assert out.closed
    assert out.channel_id not in bound(b)  # leaving the block unbound the topic
    with pytest.raises(ChannelClosed):
        out.write(3.5)


def test_an_incoming_channel_closes_and_unbinds_like_unsubscribe(
        bridge: Callable[..., Bridge]) -> None:
    b = bridge()
    out = b.publish("/vocab/in", F64, transport="tcp")
    with b.subscribe("/vocab/in", F64, transport="tcp", blocking=True, buffer_size=8) as inbox:
        assert inbox.channel_id in bound(b)
        out.write(4.0)
        assert inbox.read(timeout=WAIT) == 4.0
        assert inbox.read_many() == []
        assert isinstance(inbox.health(), ChannelHealth)
    assert inbox.channel_id not in bound(b)
    with pytest.raises(ChannelClosed):
        inbox.read(timeout=WAIT)
    other = b.subscribe("/vocab/in", F64)
    other.close()  # close() alone does what unsubscribe does
    assert other.channel_id not in bound(b)
    b.unsubscribe(other)  # and unsubscribing a closed channel again is harmless
    assert out.channel_id in bound(b)


def test_a_local_channel_is_a_context_manager_too() -> None:
    with Channel[int](4, name="local") as ch:
        ch.write(1)
        assert ch.try_read() == 1
    assert ch.closed
    with pytest.raises(ChannelClosed):
        ch.write(2)
