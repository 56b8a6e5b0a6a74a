"""``Bridge.close()`` delivers what was written before it (docs/protocol.md 8.4).

The server reads TCP and UDP independently, so a goodbye over TCP could overtake the last
datagrams, which it then dropped under a dead token, silently. The race is a matter of
timing, so each burst-then-close shape runs several times and every run must lose nothing:
small values (bundled: few datagrams), ``send(inline=True)`` after each write and 1 KB values
(a datagram per value: a long queue at the server when the goodbye goes), and TCP and UDP
channels together (the goodbye must overtake neither). A frozen server (``SIGSTOP``: its
sockets stay open, nobody answers) shows that the wait is bounded and that what the server
never confirmed is counted and said, not lost in silence.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from typing import Any

import pytest
from link_helpers import read_all, time_while_frozen

from rlbridge.client.bridge import Bridge
from rlbridge.client.options import Transport
from waiting import WAIT, wait_until

I32 = "std_msgs/msg/Int32"
STRING = "std_msgs/msg/String"
BURST = 2000
RUNS = 3
TRANSPORTS: tuple[Transport, ...] = ("tcp", "udp")


def _int(i: int) -> Any:
    return i


def _kilobyte(i: int) -> Any:
    return f"{i:06d}" + "x" * 1000


SHAPES: dict[str, tuple[str, Callable[[int], Any], bool]] = {
    # name: (type, value of i, send(inline=True) after each write)
    "small": (I32, _int, False),
    "inline": (I32, _int, True),
    "large": (STRING, _kilobyte, False),
}


@pytest.mark.parametrize("run", range(RUNS))
@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_burst_over_udp_then_close_delivers_every_value(
        bridge: Callable[..., Bridge], shape: str, run: int) -> None:
    msg_type, value, inline = SHAPES[shape]
    topic = f"/goodbye/{shape}{run}"
    sub = bridge(name="goodbye-sub")
    inbox = sub.subscribe(topic, msg_type, transport="tcp", blocking=True,
                          buffer_size=2 * BURST)
    pub = bridge(name="goodbye-pub")
    out = pub.publish(topic, msg_type, transport="udp", buffer_size=2 * BURST)
    for i in range(BURST):
        out.write(value(i))
        if inline:
            pub.send(inline=True)
    pub.close()
    assert read_all(inbox, BURST) == [value(i) for i in range(BURST)]
    assert out.statistics().overwritten == 0
    assert out.health().lost <= 0  # nothing left unconfirmed (-1: no report came)


@pytest.mark.parametrize("run", range(RUNS))
def test_burst_over_tcp_and_udp_then_close_delivers_both(
        bridge: Callable[..., Bridge], run: int) -> None:
    # Small values on TCP: a TCP batch of 1 KB values can exceed the server's frame limit.
    kinds: dict[Transport, tuple[str, Callable[[int], Any]]] = {
        "tcp": (I32, _int), "udp": (STRING, _kilobyte)}
    sub, pub = bridge(name="goodbye-sub"), bridge(name="goodbye-pub")
    inboxes = {t: sub.subscribe(f"/goodbye/mixed{run}/{t}", kinds[t][0], transport="tcp",
                                blocking=True, buffer_size=2 * BURST) for t in TRANSPORTS}
    outs = {t: pub.publish(f"/goodbye/mixed{run}/{t}", kinds[t][0], transport=t,
                           buffer_size=2 * BURST) for t in TRANSPORTS}
    for i in range(BURST):
        for t in TRANSPORTS:
            outs[t].write(kinds[t][1](i))
    pub.close()
    for t, inbox in inboxes.items():
        assert read_all(inbox, BURST) == [kinds[t][1](i) for i in range(BURST)], t


def test_close_with_nothing_in_flight_does_not_wait(
        cli_server: Callable[..., tuple[int, subprocess.Popen[str]]],
        caplog: pytest.LogCaptureFixture) -> None:
    """Once the loss reports cover every value, the goodbye goes at once: close() waits for
    no answer, so it returns even from a frozen server whose bound (60 s) would be long."""
    port, proc = cli_server("--timeout-ms", "60000")
    pub = Bridge.connect("127.0.0.1", port, name="goodbye-idle", timeout=60.0)
    out = pub.publish("/goodbye/idle", I32, transport="udp")
    out.write(1)
    wait_until(lambda: out.health().arrived == 1, "the server's report of the value")
    elapsed = time_while_frozen(proc, caplog, pub.close)
    assert elapsed < WAIT  # a close that waited for an answer would take the 60 s bound
    assert out.health().lost == 0
    assert not [r for r in caplog.records if "did not confirm" in r.getMessage()]


def test_close_when_the_server_is_frozen_is_bounded_and_counts(
        cli_server: Callable[..., tuple[int, subprocess.Popen[str]]],
        caplog: pytest.LogCaptureFixture) -> None:
    """A server that answers nothing (stopped, sockets open): close() gives up at its bound
    (the 1 s link timeout here) and counts every unconfirmed value as lost, with a warning."""
    port, proc = cli_server("--timeout-ms", "1000")
    pub = Bridge.connect("127.0.0.1", port, name="goodbye-frozen", timeout=WAIT)
    out = pub.publish("/goodbye/frozen", I32, transport="udp")
    elapsed = time_while_frozen(proc, caplog, pub.close, lambda: [out.write(i) for i in range(100)])
    assert elapsed < 1.0 + WAIT  # the bound, plus a loaded machine's worst
    assert out.health().lost == 100
    warned = [r.getMessage() for r in caplog.records if "did not confirm" in r.getMessage()]
    assert len(warned) == 1
    assert "the last 100 value(s)" in warned[0]
    assert "/goodbye/frozen" in warned[0]
