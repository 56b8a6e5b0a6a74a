"""Credit flow control end to end: a TCP every-value channel loses nothing, and a publisher
whose subscriber stops reading stops too (counts, not time)."""

from __future__ import annotations

import threading

import pytest

from rlbridge import Policy
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.server.flow import BACKLOG_SOFT

I64 = "std_msgs/msg/Int64"
SUB_WINDOW = 256
PUB_BUFFER = 1024
#: Values the path can hold while the reader reads nothing: the subscriber's ring, the
#: server's backlog for it, the publisher's ring.
HELD = SUB_WINDOW + BACKLOG_SOFT + PUB_BUFFER
COUNT = 3 * HELD


def _server_channel(bridge: Bridge, channel_id: int) -> dict[str, int]:
    channels: dict[str, dict[str, int]] = bridge.server_stats()["session"]["channels"]
    return channels[str(channel_id)]


def test_fast_publisher_slow_subscriber_loses_nothing_and_waits(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="flow-sub") as sb, \
            Bridge.connect("127.0.0.1", server.port, name="flow-pub") as pb:
        sub = sb.subscribe("/flow", I64, transport="tcp", blocking=True,
                           buffer_size=SUB_WINDOW)
        out = pb.publish("/flow", I64, transport="tcp", buffer_size=PUB_BUFFER)
        assert sub.flow
        assert out.flow

        # Phase 1: nobody reads. The publisher may write only what the path holds, then
        # its ring stays full: wait_writable gives up instead of overwriting.
        written = 0
        while written < COUNT and out.wait_writable(timeout=1.0):
            out.write(written)
            written += 1
        assert written < COUNT, "the publisher was never held back"
        assert written <= HELD, f"{written} values left a publisher whose reader reads nothing"
        assert out.writable == 0
        assert out.statistics().overwritten == 0
        arrived = _server_channel(pb, out.channel_id)["values_in"]
        assert arrived <= SUB_WINDOW + BACKLOG_SOFT
        sub_side = _server_channel(sb, sub.channel_id)
        assert sub_side["dropped"] == 0
        assert sub_side["values_out"] <= SUB_WINDOW  # never beyond the reader's credit

        # Phase 2: the reader reads slowly (in its own thread); the writer follows.
        got: list[int] = []

        def reader() -> None:
            while len(got) < COUNT:
                try:
                    got.append(sub.read(timeout=30.0))
                except TimeoutError:
                    return

        thread = threading.Thread(target=reader)
        thread.start()
        while written < COUNT:
            assert out.wait_writable(timeout=30.0)
            out.write(written)
            written += 1
        thread.join(60.0)
        assert got == list(range(COUNT))
        assert sub.lost == 0
        assert sub.statistics().overwritten == 0
        assert out.statistics().overwritten == 0
        assert _server_channel(sb, sub.channel_id)["dropped"] == 0


def test_write_many_batches_also_follow_the_reader(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="flow-sub2") as sb, \
            Bridge.connect("127.0.0.1", server.port, name="flow-pub2") as pb:
        sub = sb.subscribe("/flow2", I64, transport="tcp", blocking=True, buffer_size=64)
        out = pb.publish("/flow2", I64, transport="tcp", buffer_size=4096)
        total = 64 * 512
        got: list[int] = []

        def reader() -> None:
            while len(got) < total:
                try:
                    got.extend([sub.read(timeout=30.0), *sub.read_many()])
                except TimeoutError:
                    return

        thread = threading.Thread(target=reader)
        thread.start()
        for start in range(0, total, 512):
            while out.writable < 512:
                assert out.wait_writable(timeout=30.0)
            out.write_many(list(range(start, start + 512)))
        thread.join(60.0)
        assert got == list(range(total))
        assert out.statistics().overwritten == 0


def test_latest_and_non_blocking_channels_are_not_flow_controlled(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="flow-opts") as b:
        assert not b.subscribe("/o", I64, transport="tcp", policy=Policy(latest=True),
                               blocking=True).flow
        assert not b.subscribe("/o", I64, transport="tcp", blocking=False).flow
        assert not b.subscribe("/o", I64, transport="udp", blocking=True).flow
        assert not b.publish("/o", I64, transport="tcp", policy=Policy(latest=True)).flow
        assert not b.publish("/o", I64, transport="udp").flow
        assert b.subscribe("/o", I64, transport="tcp", blocking=False,
                           policy=Policy(flow=True)).flow
        with pytest.raises(ValueError, match=r"flow=True.*needs transport='tcp'"):
            b.publish("/o", I64, transport="udp", policy=Policy(flow=True))
        with pytest.raises(ValueError, match="flow=True, latest=True"):
            Policy(latest=True, flow=True)
