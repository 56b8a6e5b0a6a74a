"""Faults against a real ``rlbridge serve`` with the default watchdog (200 ms heartbeat, 600 ms
timeout): a client process killed with SIGKILL, and a link cut with an nftables drop rule on
loopback (which also leaves the server a half-open TCP connection). In each case the server
drops the dead session, both sides notice within the watchdog time, the cut client resumes when
the link returns, and another session on the same server keeps flowing throughout.

Timing is not asserted (a loaded machine would fail it for no bug): what is asserted is that it
was the watchdog that acted (its counter, the reason given); the measured times are printed
(``pytest -s``).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator

import pytest
from link_helpers import WAIT, roundtrip

from rlbridge.client.bridge import Bridge
from rlbridge.client.session.link_events import LinkEvent
from rlbridge.client.session.reconnect import Backoff, ClientState
from rlbridge.server import ServerConfig
from rlbridge.wire.link import LinkState
from waiting import wait_until

F64 = "std_msgs/msg/Float64"
TIMEOUT_MS = ServerConfig().timeout_ms
FAST = Backoff(initial=0.02, max_delay=0.2)


def test_default_watchdog_notices_within_three_heartbeats_and_one_second() -> None:
    cfg = ServerConfig()
    assert cfg.timeout_ms <= 3 * cfg.heartbeat_ms
    assert cfg.timeout_ms <= 1000


class Healthy:
    """Another session on the same server: a TCP and a UDP loop through the server."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.bridge = Bridge.connect("127.0.0.1", port, name="healthy", timeout=5.0,
                                     reconnect=FAST)
        self.loops = [(self.bridge.publish(f"/healthy/{t}", F64, transport=t),
                       self.bridge.subscribe(f"/healthy/{t}", F64, transport=t, blocking=True,
                                             buffer_size=256)) for t in ("tcp", "udp")]
        self.value = 0.0

    def flows(self) -> bool:
        self.value += 1.0
        return all(roundtrip(out, inbox, self.value) for out, inbox in self.loops)

    def timed_out(self) -> int:
        counters: dict[str, int] = self.bridge.server_stats()["server"]
        return counters.get("sessions_timed_out", 0)

    def topics(self) -> list[str]:
        return [name for name, _type in self.bridge.server_stats()["topics"]]


@pytest.fixture
def healthy(cli_server: Callable[..., tuple[int, subprocess.Popen[str]]]) -> Iterator[Healthy]:
    # The defaults: heartbeat 200 ms, watchdog 600 ms (the watchdog is what these tests test).
    port, _proc = cli_server("--timeout-ms", str(TIMEOUT_MS))
    h = Healthy(port)
    assert h.flows()
    yield h
    h.bridge.close()


# -- a client process dies -----------------------------------------------------------------

VICTIM = textwrap.dedent("""
    import sys, time
    from rlbridge import Bridge, Tuning
    port, control = int(sys.argv[1]), sys.argv[2]
    b = Bridge.connect("127.0.0.1", port, tuning=Tuning(control=control), name="victim",
                       timeout=5.0)
    b.subscribe(f"/victim/{control}", "std_msgs/msg/Float64", transport="udp")
    out = b.publish(f"/victim/{control}/out", "std_msgs/msg/Float64", transport="udp")
    print("ready", flush=True)
    for i in range(60_000):  # bounded: 10 minutes at most
        out.write(float(i))
        time.sleep(0.01)
""")


@pytest.mark.parametrize("control", ["tcp", "udp"])
def test_killed_client_is_dropped_and_other_sessions_keep_flowing(
        healthy: Healthy, control: str) -> None:
    port = healthy.port
    victim = subprocess.Popen([sys.executable, "-c", VICTIM, str(port), control],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert victim.stdout is not None
        assert victim.stdout.readline().strip() == "ready", victim.stderr
        topic = f"/victim/{control}"
        assert topic in healthy.topics()
        timed_out = healthy.timed_out()
        victim.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        victim.wait(WAIT)
        wait_until(lambda: topic not in healthy.topics(),
                   "the server to drop the dead session", timeout=WAIT)
        dropped_ms = (time.monotonic() - killed) * 1e3
    finally:
        if victim.poll() is None:
            victim.kill()
        victim.communicate(timeout=WAIT)
    print(f"\nclient killed (control {control}): session dropped after {dropped_ms:.0f} ms")
    if control == "udp":  # no FIN: only the watchdog can tell
        assert healthy.timed_out() == timed_out + 1
    assert healthy.flows()
    assert healthy.bridge.reconnects == 0


# -- the link is cut -----------------------------------------------------------------------


class NftCut:
    """An nftables table that drops loopback traffic of one server port except some ports."""

    def __init__(self) -> None:
        self.table = f"rlbridge_reconnect_{os.getpid()}"
        self.active = False

    def cut(self, server_port: int, keep: dict[str, int]) -> None:
        rules = "\n".join(
            f"iifname \"lo\" {proto} {a} {server_port} {proto} {b} != {keep[proto]} drop"
            for proto in ("tcp", "udp") for a, b in (("dport", "sport"), ("sport", "dport")))
        script = (f"table inet {self.table} {{\n chain input {{\n"
                  f"  type filter hook input priority -10; policy accept;\n{rules}\n }}\n}}\n")
        subprocess.run(["nft", "-f", "-"], input=script, text=True, check=True,
                       capture_output=True)
        self.active = True

    def restore(self) -> None:
        if self.active:
            subprocess.run(["nft", "delete", "table", "inet", self.table], check=True,
                           capture_output=True)
            self.active = False


@pytest.fixture
def nft() -> Iterator[NftCut]:
    if os.geteuid() != 0 or shutil.which("nft") is None:
        reason = "cutting the link needs root and nft (nftables)"
        print(f"\nskipped: {reason}")
        pytest.skip(reason)
    probe = subprocess.run(["nft", "list", "tables"], capture_output=True, text=True,
                           check=False)
    if probe.returncode != 0:
        reason = f"nft does not work here: {probe.stderr.strip()}"
        print(f"\nskipped: {reason}")
        pytest.skip(reason)
    cut = NftCut()
    try:
        yield cut
    finally:
        cut.restore()


def test_cut_link_is_noticed_by_both_sides_and_the_client_resumes_when_it_returns(
        healthy: Healthy, nft: NftCut) -> None:
    port = healthy.port
    victim = Bridge.connect("127.0.0.1", port, name="cut", timeout=2.0, reconnect=FAST)
    try:
        loops = [(victim.publish(f"/cut/{t}", F64, transport=t),
                  victim.subscribe(f"/cut/{t}", F64, transport=t, blocking=True,
                                   buffer_size=256)) for t in ("tcp", "udp")]
        assert all(roundtrip(out, inbox, 1.0) for out, inbox in loops)
        events = victim.link_events()
        events.read_many()
        timed_out = healthy.timed_out()

        cut_at = time.monotonic_ns()
        nft.cut(port, healthy.bridge.local_ports)  # every client of the port but the healthy one
        seen: list[LinkEvent] = []

        def told() -> bool:  # link_state says lost a moment before the event is written
            seen.extend(events.read_many())
            return any(e.state is LinkState.LOST for e in seen)
        wait_until(lambda: victim.link_state is LinkState.LOST and told(),
                   "the client to notice", timeout=WAIT)
        lost = next(e for e in seen if e.state is LinkState.LOST)
        client_ms = (lost.at_ns - cut_at) / 1e6
        # The victim's TCP connection is half-open on the server now: no FIN, no RST came.
        wait_until(lambda: healthy.timed_out() > timed_out, "the server's watchdog", timeout=WAIT)
        server_ms = (time.monotonic_ns() - cut_at) / 1e6
        print(f"\nlink cut: client noticed after {client_ms:.0f} ms ({lost.reason}); server "
              f"reaped the half-open session within {server_ms:.0f} ms (watchdog {TIMEOUT_MS} ms)")
        assert "watchdog" in lost.reason
        assert healthy.timed_out() == timed_out + 1  # only the cut session
        assert healthy.flows()  # undisturbed meanwhile
        assert victim.state is ClientState.RECONNECTING

        nft.restore()
        wait_until(lambda: victim.reconnects >= 1 and victim.link_state is LinkState.CONNECTED,
                   "the client to resume once the link is back", timeout=WAIT)
        assert all(roundtrip(out, inbox, 2.0) for out, inbox in loops)
        assert healthy.flows()
        assert healthy.bridge.reconnects == 0
    finally:
        victim.close()
