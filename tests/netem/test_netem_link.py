"""EmulatedLink with real namespaces, TUN devices and the relay process (needs root).

Timing assertions are lower bounds only, and strict (the relay never releases a packet early):
an upper bound would fail on a loaded machine for no fault of the emulator. What the relay adds
is a benchmark figure (``rlbridge netem calibrate``, docs/netem.md).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rlbridge.netem
import rlbridge.netem.link
from rlbridge.netem import (
    DropReason,
    EmulatedLink,
    Impairment,
    PathModel,
    cleanup_stale_namespaces,
    emulator_unavailable_reason,
    find_stale_namespaces,
)
from rlbridge.netem.netns import create_namespace, delete_namespace, list_namespaces
from rlbridge.netem.probe import measure_overhead, summarize, udp_ping_pong
from waiting import wait_until

pytestmark = [pytest.mark.netem, pytest.mark.timeout(60)]

SO_RCVBUFFORCE = 33
IP_MTU_DISCOVER = 10
IP_PMTUDISC_DO = 2


@pytest.fixture(scope="module", autouse=True)
def _require_emulator() -> None:
    reason = emulator_unavailable_reason()
    if reason is not None:
        pytest.skip(f"network emulator unavailable: {reason}")


UdpPair = Callable[[EmulatedLink], tuple[socket.socket, socket.socket]]


@pytest.fixture
def udp_pair() -> Iterator[UdpPair]:
    """A factory for bound UDP sockets on both sides of a link, closed after the test."""
    opened: list[socket.socket] = []

    def make(link: EmulatedLink) -> tuple[socket.socket, socket.socket]:
        a = link.open_socket("a")
        b = link.open_socket("b")
        opened.extend([a, b])
        a.bind((link.addr_a, 0))
        b.bind((link.addr_b, 0))
        a.settimeout(5.0)
        b.settimeout(5.0)
        return a, b

    yield make
    for sock in opened:
        sock.close()


def child_env() -> dict[str, str]:
    """Environment under which a child Python can import this rlbridge."""
    src = str(Path(rlbridge.netem.__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
    return env


def wait_gone(pid: int, timeout_s: float) -> bool:
    """True once ``pid`` has exited (zombies count as exited), within ``timeout_s``."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        readable, _, _ = select.select([fd], [], [], timeout_s)
        return bool(readable)
    finally:
        os.close(fd)


def test_udp_rtt_at_0_and_5_ms(udp_pair: UdpPair) -> None:
    with EmulatedLink(delay_ms=0.0) as link:
        a, b = udp_pair(link)
        clean = summarize(udp_ping_pong(a, b, count=100), 100)
        link.set_impairment(delay_ms=5.0)
        delayed = summarize(udp_ping_pong(a, b, count=60), 60)
    print(f"\nclean: {clean}\n5 ms:  {delayed}")
    assert clean.lost == 0
    assert delayed.lost == 0
    assert delayed.min_us >= 10_000  # strict: 2 x 5 ms, never early
    assert clean.min_us < delayed.min_us  # the delay is the impairment's, not always there


def test_one_direction_only(udp_pair: UdpPair) -> None:
    with EmulatedLink(delay_ms=5.0, direction="a_to_b") as link:
        a, b = udp_pair(link)
        forward, backward = [], []
        for seq in range(40):
            t0 = time.monotonic()
            a.sendto(struct.pack("!I", seq), b.getsockname())
            data, sender = b.recvfrom(100)
            t1 = time.monotonic()
            b.sendto(data, sender)
            a.recv(100)
            forward.append(t1 - t0)
            backward.append(time.monotonic() - t1)
        stats = link.stats()
    assert min(forward) >= 0.005
    assert sorted(backward)[20] < 0.005  # median of the clean direction
    assert stats.a_to_b.delivered == stats.b_to_a.delivered == 40


def _stats_when(link: EmulatedLink, done: Callable[[Any], bool]) -> Any:
    """The link's counters if ``done`` says they are complete, else None (ask again)."""
    stats = link.stats()
    return stats if done(stats) else None


def test_seeded_loss_is_counted_by_relay_and_seen_by_receiver(udp_pair: UdpPair) -> None:
    count, seed = 400, 7
    with EmulatedLink(loss_pct=10.0, seed=seed, direction="a_to_b") as link:
        a, b = udp_pair(link)
        b.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 4 << 20)
        for seq in range(count):
            a.sendto(struct.pack("!I", seq), b.getsockname())
        stats = wait_until(lambda: _stats_when(link, lambda s: s.a_to_b.received >= count),
                           f"the relay to take all {count} datagrams")
        b.setblocking(False)
        received = set()
        with contextlib.suppress(BlockingIOError):
            while True:
                received.add(struct.unpack("!I", b.recv(100))[0])
    # The relay saw every datagram (nothing else crosses the link), dropped some on
    # purpose, and the receiver got exactly the others.
    assert stats.a_to_b.received == count
    assert stats.a_to_b.dropped_loss == count - len(received)
    assert stats.a_to_b.delivered == len(received)
    assert stats.b_to_a.received == 0
    assert 15 <= stats.a_to_b.dropped_loss <= 70  # 10 % of 400, +- 4 sd
    # Seeded: the very same datagrams as the pure model says.
    model = PathModel(Impairment(loss_pct=10.0), seed=seed, name="a_to_b")
    lost = {s for s in range(count) if isinstance(model.admit(0.0, 32), DropReason)}
    assert received == set(range(count)) - lost


def test_flood_every_packet_is_accounted_for(udp_pair: UdpPair) -> None:
    """Relay counters plus kernel TUN drops add up to what was sent, even when flooded."""
    count = 5000
    with EmulatedLink() as link:
        a, b = udp_pair(link)
        b.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 16 << 20)
        for _ in range(count):
            a.sendto(bytes(64), b.getsockname())

        def accounted() -> tuple[Any, int] | None:
            stats = link.stats()
            dropped_a, _ = link.kernel_drops()
            done = stats.a_to_b.received + dropped_a >= count and stats.a_to_b.in_flight == 0
            return (stats, dropped_a) if done else None

        stats, dropped_a = wait_until(accounted, "every packet to be accounted for",
                                      interval=0.05)
    assert stats.a_to_b.received + dropped_a == count
    assert stats.a_to_b.delivered == stats.a_to_b.received


def test_tcp_works_and_survives_loss() -> None:
    payload = os.urandom(150_000)
    with EmulatedLink(delay_ms=1.0, seed=3) as link:
        with link.open_socket("b", socket.SOCK_STREAM) as server:
            server.bind((link.addr_b, 0))
            server.listen(1)
            server.settimeout(5.0)
            with link.open_socket("a", socket.SOCK_STREAM) as client:
                client.settimeout(20.0)
                client.connect(server.getsockname())
                conn, _ = server.accept()
                with conn:
                    conn.settimeout(20.0)
                    link.set_impairment(delay_ms=1.0, loss_pct=10.0)
                    sender = threading.Thread(target=client.sendall, args=(payload,))
                    sender.start()
                    chunks = []
                    remaining = len(payload)
                    while remaining:
                        chunk = conn.recv(65536)
                        assert chunk, "connection closed early"
                        chunks.append(chunk)
                        remaining -= len(chunk)
                    sender.join(timeout=20.0)
                    assert not sender.is_alive()
        stats = link.stats()
    assert hashlib.sha256(b"".join(chunks)).digest() == hashlib.sha256(payload).digest()
    dropped = stats.a_to_b.dropped_loss + stats.b_to_a.dropped_loss
    assert dropped > 0, "the link should have dropped segments that TCP then retransmitted"


def test_rate_limit_and_realtime_relay(udp_pair: UdpPair) -> None:
    with EmulatedLink(relay_rt_priority=10) as link:
        assert link.relay_pid is not None
        assert os.sched_getscheduler(link.relay_pid) == os.SCHED_FIFO
        a, b = udp_pair(link)
        # 1000-byte datagrams are 1028-byte packets: 8224 bits, about 10.3 ms at 800 kbit/s.
        link.set_impairments(Impairment(rate_kbit=800.0), Impairment())
        assert link.impairments[0].rate_kbit == 800.0
        start = time.monotonic()
        for _ in range(20):
            a.sendto(bytes(1000), b.getsockname())
        for _ in range(20):
            b.recv(2000)
        elapsed = time.monotonic() - start
    assert elapsed >= 20 * 8224 / 800_000 - 1e-3  # serialisation of all twenty, never faster


def test_mtu_is_enforced_and_fragments_cross(udp_pair: UdpPair) -> None:
    with EmulatedLink(mtu=1500) as link:
        a, b = udp_pair(link)
        a.setsockopt(socket.IPPROTO_IP, IP_MTU_DISCOVER, IP_PMTUDISC_DO)
        a.sendto(b"m" * 1472, b.getsockname())  # 1472 + 8 + 20 = 1500
        assert len(b.recv(2000)) == 1472
        with pytest.raises(OSError, match="Message too long"):
            a.sendto(b"m" * 1473, b.getsockname())
        before = link.stats().a_to_b.received
        with link.open_socket("a") as frag:
            frag.sendto(b"f" * 4000, b.getsockname())  # default: fragment
        assert len(b.recv(5000)) == 4000
        assert link.stats().a_to_b.received - before == 3  # 3 fragments of <= 1500 bytes


def test_popen_in_runs_inside_the_namespace(udp_pair: UdpPair) -> None:
    with EmulatedLink() as link:
        _, b = udp_pair(link)
        host, port = b.getsockname()
        script = f"import socket; socket.socket(2, 2).sendto(b'hello from A', ({host!r}, {port}))"
        proc = link.popen_in("a", [sys.executable, "-c", script])
        assert proc.wait(timeout=10) == 0
        assert b.recv(100) == b"hello from A"
        routes = link.run_in("b", ["ip", "route"], timeout=5, capture_output=True, text=True)
        assert link.addr_a in routes.stdout
        assert link.run_in("a", ["ip", "-o", "link"], timeout=5, capture_output=True, text=True)


def test_teardown_leaves_no_namespace_relay_or_process() -> None:
    with EmulatedLink() as link:
        names = (link.ns_a, link.ns_b)
        relay_pid = link.relay_pid
        assert relay_pid is not None
        assert set(names) <= set(list_namespaces())
        child = link.popen_in("b", ["sleep", "30"])
        # A grandchild we do not hold a Popen for: found through `ip netns pids`.
        shell = link.popen_in(
            "a", ["sh", "-c", "sleep 30 & echo $!; wait"], stdout=subprocess.PIPE, text=True
        )
        assert shell.stdout is not None
        grandchild = int(shell.stdout.readline())
        shell.stdout.close()
    assert not set(names) & set(list_namespaces())
    assert wait_gone(relay_pid, 1.0)
    assert child.returncode is not None
    assert shell.returncode is not None
    assert wait_gone(grandchild, 3.0)
    assert link.relay_pid is None
    with pytest.raises(RuntimeError, match="not started"):
        link.stats()


def test_crash_in_body_still_cleans_up() -> None:
    class BodyError(Exception):
        pass

    seen: dict[str, object] = {}

    def body() -> None:
        with EmulatedLink(delay_ms=3.0) as link:
            seen.update(names={link.ns_a, link.ns_b}, relay_pid=link.relay_pid)
            raise BodyError

    with pytest.raises(BodyError):
        body()
    assert isinstance(seen["names"], set)
    assert not seen["names"] & set(list_namespaces())
    assert isinstance(seen["relay_pid"], int)
    assert wait_gone(seen["relay_pid"], 1.0)


def test_failed_start_undoes_what_it_did(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise OSError("injected failure while configuring the TUN")

    monkeypatch.setattr(rlbridge.netem.link, "configure_point_to_point", broken)
    link = EmulatedLink()
    with pytest.raises(OSError, match="injected"):
        link.start()
    assert not {link.ns_a, link.ns_b} & set(list_namespaces())
    link.close()  # still safe


def test_sigterm_tears_the_link_down() -> None:
    script = textwrap.dedent(
        """
        import time
        from rlbridge.netem import EmulatedLink
        with EmulatedLink(delay_ms=1.0, max_lifetime_s=30.0) as link:
            print(link.ns_a, link.ns_b, link.relay_pid, flush=True)
            time.sleep(30)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=child_env()
    )
    try:
        assert proc.stdout is not None
        ns_a, ns_b, relay_pid = proc.stdout.readline().split()
        assert {ns_a, ns_b} <= set(list_namespaces())
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    assert not {ns_a, ns_b} & set(list_namespaces())
    assert wait_gone(int(relay_pid), 1.0)


def test_sigkill_relay_exits_and_stale_cleanup_removes_namespaces() -> None:
    script = textwrap.dedent(
        """
        import time
        from rlbridge.netem import EmulatedLink
        with EmulatedLink(max_lifetime_s=30.0) as link:
            print(link.ns_a, link.ns_b, link.relay_pid, flush=True)
            time.sleep(30)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=child_env()
    )
    try:
        assert proc.stdout is not None
        ns_a, ns_b, relay_pid = proc.stdout.readline().split()
        proc.kill()  # no chance to clean up
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
    try:
        # The relay notices the closed control socket and exits on its own ...
        assert wait_gone(int(relay_pid), 5.0)
        # ... the namespaces stay until a stale cleanup, which recognises them as stale
        # (a parallel test run may clean them up first; then they are simply gone).
        names = {ns_a, ns_b}
        stale = {ns.name for ns in find_stale_namespaces()}
        assert names <= stale | (names - set(list_namespaces()))
        cleanup_stale_namespaces()
        assert not names & set(list_namespaces())
    finally:
        for name in (ns_a, ns_b):
            delete_namespace(name)


def test_stale_cleanup_keeps_namespaces_of_live_processes() -> None:
    mine = f"rlb-{os.getpid()}-{os.urandom(3).hex()}-a"
    create_namespace(mine)
    try:
        removed = {ns.name for ns in cleanup_stale_namespaces()}
        assert mine not in removed
        assert mine in list_namespaces()
    finally:
        delete_namespace(mine)


def test_relay_overhead_is_small() -> None:
    with EmulatedLink() as link:
        result = measure_overhead(link, count=300)
    print(
        f"\nlink {result.link}\nloopback {result.loopback}\n"
        f"added median {result.added_median_us:.0f} us, "
        f"relay lateness mean {result.relay_late_mean_us:.0f} us"
    )
    assert result.link.lost == 0
    assert result.loopback.lost == 0
    # What the relay adds (well under the thesis's smallest delay, 3 ms, on an idle machine)
    # is a figure for `rlbridge netem calibrate` (docs/netem.md), not a bound for a test.
