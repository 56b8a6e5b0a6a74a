"""Loss feedback and rate limits on UDP publish channels, against a live server.

The lossy path is real: the server's event loop is stalled while the client floods, so the
kernel's receive buffer of the server's UDP socket (4 MiB asked here, ``udp_receive_buffer``;
the default, 32 MiB, would hold a flood) overflows and drops datagrams; the
server counts the gaps and reports them. Asserted is the mechanism (a report arrives and
names the loss; health and link events show it; the counts match the server's own), not
how fast.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest
from link_helpers import WAIT

from rlbridge import Policy
from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.incoming import OutgoingChannel
from rlbridge.server import ServerThread
from waiting import poll_until, wait_until

F64 = "std_msgs/msg/Float64"
CHUNK = 1000
#: Values per flood: ~11 MB of datagrams, more than the server's receive buffer holds.
FLOOD = 600 * CHUNK


@pytest.fixture
def server(make_server: Callable[..., ServerThread]) -> ServerThread:
    """A server whose UDP receive buffer one flood overflows."""
    return make_server(udp_receive_buffer=4 << 20)


def _stall(server: ServerThread, seconds: float) -> None:
    """Block the server's event loop (not the process) for ``seconds``, from now."""
    loop = server.server._loop
    assert loop is not None
    started = threading.Event()

    def stall() -> None:
        started.set()
        time.sleep(seconds)

    loop.call_soon_threadsafe(stall)
    assert started.wait(10.0)


def _flood_until_lost(server: ServerThread, bridge: Bridge, out: OutgoingChannel) -> None:
    """Flood through a stalled server until a loss report arrives (bounded attempts)."""
    for _attempt in range(5):
        _stall(server, 1.0)
        for start in range(0, FLOOD, CHUNK):
            out.write_many([float(x) for x in range(start, start + CHUNK)])
            bridge.send(wait=True)
        if poll_until(lambda: out.health().lost > 0, timeout=5.0, interval=0.02):
            return
    raise AssertionError("five floods through a stalled server and no loss was reported")


def test_udp_flood_loss_is_reported_to_the_publisher(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="flood") as b:
        events = b.link_events()
        out = b.publish("/flood", F64, transport="udp", buffer_size=4 * CHUNK)
        assert out.health().lost == -1  # no report yet
        assert out.health().arrived == -1
        _flood_until_lost(server, b, out)
        health = out.health()
        assert health.lost > 0
        assert health.arrived > 0
        loss_events = [e for e in events.read_many() if e.channel == out.channel_id]
        assert loss_events
        assert all(e.lost > 0 for e in loss_events)
        assert "lost at the first hop" in loss_events[0].reason
        assert b.link_state.value == "connected"  # loss is an event, not a state

        # The report tells what the server counted (cumulative: the next one catches up).
        def same_as_server() -> bool:
            ch = b.server_stats()["session"]["channels"][str(out.channel_id)]
            h = out.health()
            return bool(ch["lost"] == h.lost and ch["values_in"] == h.arrived)

        wait_until(same_as_server, "the reported counts to match the server's", timeout=WAIT)


def test_adaptive_rate_backs_off_on_reported_loss(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="adapt") as b:
        top = 10_000_000
        out = b.publish("/adapt", F64, transport="udp", buffer_size=4 * CHUNK,
                        policy=Policy(max_rate_hz=top, adapt_rate=True))
        assert out.health().rate_limit_hz == top
        _flood_until_lost(server, b, out)
        wait_until(lambda: out.health().rate_limit_hz < top, "the rate to back off", timeout=WAIT)


def test_rate_limit_holds_values_in_the_ring_and_loses_none(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, name="limit") as sub_b, \
            Bridge.connect("127.0.0.1", server.port, name="limited") as b:
        inbox = sub_b.subscribe("/limited", F64, transport="tcp", blocking=True,
                                buffer_size=256)
        out = b.publish("/limited", F64, transport="udp", buffer_size=256,
                        policy=Policy(max_rate_hz=20))
        out.write_many([float(i) for i in range(40)])  # two seconds' worth at 20 Hz
        b.send()
        assert out.pending() > 0, "a rate-limited channel sent 40 values at once"
        got = [inbox.read(timeout=30.0) for _ in range(40)]
        assert got == [float(i) for i in range(40)]
        assert out.pending() == 0
        assert out.statistics().overwritten == 0
        assert out.health().rate_limit_hz == 20
        out.write_many([float(i) for i in range(10)])
        b.send(wait=True)  # waits for the rate limit too
        assert out.pending() == 0


#: Bundled flood: channels, and values per channel and round (4 x 34 Float64 parts: one
#: datagram of ~1,300 bytes per round, so a lost datagram loses a part of every channel).
BUNDLED = 4
PER_ROUND = 34
#: Rounds per flood at most (~13 MB of datagrams); each flood also ends with its stall.
ROUNDS = 10_000


def test_bundled_flood_loss_is_reported_per_channel_as_the_server_counted(
        server: ServerThread) -> None:
    """Values of several channels in one datagram (bundles): each channel's report counts
    its own parts, arrived and lost, exactly as the server's per-channel counters do."""
    with Bridge.connect("127.0.0.1", server.port, name="bundled-flood") as b:
        outs = [b.publish(f"/bflood/c{i}", F64, transport="udp", buffer_size=4 * CHUNK)
                for i in range(BUNDLED)]
        sender = b._sender
        for _attempt in range(5):
            _stall(server, 2.0)
            stall_end = time.monotonic() + 2.0
            for start in range(0, ROUNDS * PER_ROUND, PER_ROUND):
                chunk = [float(x) for x in range(start, start + PER_ROUND)]
                for out in outs:
                    out.write_many(chunk)
                b.send(wait=True)
                if time.monotonic() > stall_end:
                    break
            if poll_until(lambda: min(o.health().lost for o in outs) > 0, timeout=5.0,
                          interval=0.02):
                break
        else:
            raise AssertionError("five bundled floods through a stalled server, no loss reported")
        # The channels' parts shared datagrams: fewer datagrams than packets left the SDK.
        assert sender.datagrams < sender.packets_sent

        def same_as_server() -> bool:
            channels = b.server_stats()["session"]["channels"]
            for out in outs:
                ch, h = channels[str(out.channel_id)], out.health()
                if not (ch["lost"] == h.lost and ch["values_in"] == h.arrived):
                    return False
            return True

        wait_until(same_as_server,
                   "every channel's reported counts to match the server's", timeout=WAIT)
        sent = [o.statistics().read for o in outs]
        for out, taken in zip(outs, sent, strict=True):
            h = out.health()
            assert h.arrived + h.lost <= taken  # nothing counted that was not sent
