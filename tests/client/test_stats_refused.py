"""A refused request fails at once with the server's reason (client/session/pending.py).

A UDP-only session's ``Stats`` answer can be too large for a datagram; the server then
answers ``Error(3 TOO_LARGE)`` saying to ask over TCP (protocol.md 12.2). The client used to
log that Error and let ``server_stats()`` wait out its whole timeout, then blame the server for
not answering. A server with 300 topics of 250-character names (about 80 kB of topic list)
makes the answer too large.
"""

from __future__ import annotations

import pytest

from rlbridge import ErrorCode
from rlbridge.adapters.base import QoS
from rlbridge.adapters.inproc import InProcessBus
from rlbridge.client.bridge import Bridge
from rlbridge.client.options import Tuning
from rlbridge.errors import ConnectionFailed, RemoteError
from rlbridge.server import ServerThread

F64 = "std_msgs/msg/Float64"
#: Longer than a loaded machine needs for an answer on loopback: the old code raised
#: ``ConnectionFailed`` (no answer) after it, the fixed one raises the refusal before.
PATIENCE = 30.0


def _many_topics(server: ServerThread) -> None:
    registry = server.server.registry
    assert registry is not None
    bus = registry.ctx.adapter
    assert isinstance(bus, InProcessBus)
    for n in range(300):
        bus.create_publisher(f"/many/n{n:03d}/" + "t" * 240, F64, "data", QoS())


def test_udp_only_stats_too_large_for_a_datagram_raise_the_servers_reason(
        server: ServerThread) -> None:
    _many_topics(server)
    with Bridge.connect("127.0.0.1", server.port, name="stats-over-udp",
                        tuning=Tuning(control="udp"), timeout=PATIENCE) as bridge:
        with pytest.raises(RemoteError) as refused:
            bridge.server_stats()
        assert not isinstance(refused.value, ConnectionFailed)
        assert refused.value.code == ErrorCode.TOO_LARGE
        assert refused.value.channel is None
        assert "ask over TCP" in refused.value.reason
        assert "statistics refused" in str(refused.value)
        # The session goes on: a small request is answered.
        channel = bridge.subscribe("/still/here", F64, transport="udp")
        assert channel.msg_type == F64


def test_over_tcp_the_same_stats_are_answered(server: ServerThread) -> None:
    _many_topics(server)
    with Bridge.connect("127.0.0.1", server.port, name="stats-over-tcp",
                        timeout=PATIENCE) as bridge:
        topics = bridge.server_stats()["topics"]
    assert len([name for name, _ in topics if name.startswith("/many/")]) == 300
