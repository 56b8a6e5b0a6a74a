"""``channel.close()`` delivers what was written before it (docs/protocol.md 8.4).

Closing a UDP publish channel unbinds it with a ``TopicClose`` over TCP, which the server,
reading TCP and UDP independently, could handle before the channel's last datagrams: it then
dropped them (the channel was gone), silently. The session stays up here, unlike
``Bridge.close()`` (tests/client/test_close_goodbye.py): only the binding ends. 1 KB values (a
datagram each: a long queue at the server when the close goes) reproduced it most often, so
each shape runs several times and every run must lose nothing. A frozen server shows that the
wait is bounded and what it never confirmed is counted and said; with nothing in flight,
close() waits for no answer at all.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from typing import Any

import pytest
from link_helpers import read_all, time_while_frozen

from rlbridge.client.bridge import Bridge
from waiting import WAIT, wait_until

I32 = "std_msgs/msg/Int32"
STRING = "std_msgs/msg/String"
BURST = 2000
RUNS = 5


def _kilobyte(i: int) -> Any:
    return f"{i:06d}" + "x" * 1000


@pytest.mark.parametrize("run", range(RUNS))
@pytest.mark.parametrize("shape", ["immediate", "buffered", "flushed"])
def test_burst_over_udp_then_channel_close_delivers_every_value(
        bridge: Callable[..., Bridge], shape: str, run: int) -> None:
    """``immediate``: close() right after the writes, values still in the channel;
    ``buffered``: ``through_buffer`` and one ``send()``; ``flushed``: ``send(wait=True)``
    first, so every datagram is in the kernel and only the TopicClose can overtake them."""
    through_buffer = shape == "buffered"
    topic = f"/unbind/{shape}{run}"
    sub = bridge(name="unbind-sub")
    inbox = sub.subscribe(topic, STRING, transport="tcp", blocking=True,
                          buffer_size=2 * BURST)
    pub = bridge(name="unbind-pub")
    out = pub.publish(topic, STRING, transport="udp", buffer_size=2 * BURST,
                      through_buffer=through_buffer)
    for i in range(BURST):
        out.write(_kilobyte(i))
    if shape != "immediate":
        pub.send(wait=shape == "flushed")
    out.close()
    assert read_all(inbox, BURST) == [_kilobyte(i) for i in range(BURST)]
    assert out.health().lost <= 0  # nothing left unconfirmed (-1: no report came)
    assert not pub.closed  # the session goes on: a new channel on it works
    again = pub.publish(topic, STRING, transport="udp")
    again.write("after")
    assert read_all(inbox, 1) == ["after"]


def test_channel_close_with_nothing_in_flight_does_not_wait(
        cli_server: Callable[..., tuple[int, subprocess.Popen[str]]],
        caplog: pytest.LogCaptureFixture) -> None:
    """Once the loss reports cover every value, the TopicClose goes at once: close() waits
    for no answer, so it returns even from a frozen server whose bound (60 s) would be long."""
    port, proc = cli_server("--timeout-ms", "60000")
    with Bridge.connect("127.0.0.1", port, name="unbind-idle", timeout=60.0) as pub:
        out = pub.publish("/unbind/idle", I32, transport="udp")
        out.write(1)
        wait_until(lambda: out.health().arrived == 1, "the server's report of the value")
        elapsed = time_while_frozen(proc, caplog, out.close)
        assert elapsed < WAIT  # a close that waited for an answer would take the 60 s bound
        assert out.health().lost == 0
        assert not [r for r in caplog.records if "did not confirm" in r.getMessage()]


def test_channel_close_when_the_server_is_frozen_is_bounded_and_counts(
        cli_server: Callable[..., tuple[int, subprocess.Popen[str]]],
        caplog: pytest.LogCaptureFixture) -> None:
    """A server that answers nothing: close() gives up at its bound (the 1 s link timeout
    here), unbinds anyway, and counts every unconfirmed value as lost, with a warning."""
    port, proc = cli_server("--timeout-ms", "1000")
    pub = Bridge.connect("127.0.0.1", port, name="unbind-frozen", timeout=WAIT)
    try:
        out = pub.publish("/unbind/frozen", I32, transport="udp")

        def write_then_close() -> None:
            for i in range(100):
                out.write(i)
            out.close()

        elapsed = time_while_frozen(proc, caplog, write_then_close)
        assert elapsed < 1.0 + WAIT  # the bound, plus a loaded machine's worst
        assert out.health().lost == 100
        warned = [r.getMessage() for r in caplog.records if "did not confirm" in r.getMessage()]
        assert len(warned) == 1
        assert "the last 100 value(s)" in warned[0]
        assert "/unbind/frozen" in warned[0]
    finally:
        pub.close()
