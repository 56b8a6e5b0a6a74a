"""The relay loop with socket pairs standing in for the TUN devices (no root needed).

A ``SOCK_DGRAM`` unix socket pair behaves like a TUN descriptor for the relay: one
``read`` is one packet, one ``write`` is one packet.  The relay runs in a thread here;
in production it is a process of its own.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from rlbridge.netem import control
from rlbridge.netem.impairment import DropReason, Impairment, PathModel
from rlbridge.netem.relay import Relay
from rlbridge.netem.stats import DirectionCounters
from waiting import wait_until

pytestmark = pytest.mark.timeout(30)


@dataclass
class Harness:
    app_a: socket.socket
    app_b: socket.socket
    ctrl: socket.socket
    thread: threading.Thread

    def request(self, message: control.Request) -> control.Reply:
        self.ctrl.send(control.encode(message))
        return control.decode_reply(self.ctrl.recv(control.MAX_MESSAGE_BYTES))


MakeRelay = Callable[..., Harness]


@pytest.fixture
def make_relay() -> Iterator[MakeRelay]:
    opened: list[socket.socket] = []
    controls: list[socket.socket] = []
    threads: list[threading.Thread] = []

    def make(a_to_b: Impairment, b_to_a: Impairment, lifetime_s: float = 20.0) -> Harness:
        app_a, relay_a = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        app_b, relay_b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        ctrl, relay_ctrl = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        opened.extend([app_a, relay_a, app_b, relay_b, ctrl, relay_ctrl])
        controls.append(ctrl)
        for sock in (relay_a, relay_b):
            sock.setblocking(False)
        for sock in (app_a, app_b, ctrl):
            sock.settimeout(5.0)
        relay = Relay(
            tun_a=relay_a.fileno(),
            tun_b=relay_b.fileno(),
            ctrl=relay_ctrl,
            models=(
                PathModel(a_to_b, seed=1, name="a_to_b"),
                PathModel(b_to_a, seed=1, name="b_to_a"),
            ),
            deadline=time.monotonic() + lifetime_s,
        )
        thread = threading.Thread(target=relay.run, daemon=True)
        thread.start()
        threads.append(thread)
        harness = Harness(app_a, app_b, ctrl, thread)
        assert isinstance(control.decode_reply(ctrl.recv(control.MAX_MESSAGE_BYTES)), control.Ready)
        return harness

    yield make
    for sock in controls:
        sock.close()  # EOF stops a relay that is still running
    for thread in threads:
        thread.join(timeout=5.0)
        assert not thread.is_alive()
    for sock in opened:
        sock.close()


def test_delays_one_direction_and_keeps_order(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(delay_ms=20.0), Impairment())
    sent_at = []
    for seq in range(10):
        sent_at.append(time.monotonic())
        h.app_a.send(struct.pack("!I", seq))
    for seq in range(10):
        data = h.app_b.recv(100)
        arrived = time.monotonic()
        assert struct.unpack("!I", data)[0] == seq
        assert arrived - sent_at[seq] >= 0.020  # never early: strict lower bound
    h.app_b.send(b"back")
    assert h.app_a.recv(100) == b"back"

    # No upper bound on the time (a loaded machine is slow for no fault of the relay): the
    # relay's own counters say each packet went through once, in its direction.
    reply = h.request(control.GetStats())
    assert isinstance(reply, control.StatsReply)
    assert reply.stats.a_to_b.received == reply.stats.a_to_b.delivered == 10
    assert reply.stats.b_to_a.received == reply.stats.b_to_a.delivered == 1
    assert reply.stats.a_to_b.bytes_delivered == 40
    assert reply.stats.b_to_a.delivered == 1
    assert reply.stats.a_to_b.in_flight == 0


def _stats_once(h: Harness, done: Callable[[control.StatsReply], bool]
                ) -> control.StatsReply | None:
    """The relay's counters if ``done`` says they are complete, else None (ask again)."""
    reply = h.request(control.GetStats())
    assert isinstance(reply, control.StatsReply)
    return reply if done(reply) else None


def test_loss_is_counted_and_matches_the_model(make_relay: MakeRelay) -> None:
    imp = Impairment(loss_pct=30.0)
    h = make_relay(imp, Impairment())
    for seq in range(200):
        h.app_a.send(struct.pack("!I", seq))
        if seq % 20 == 19:
            time.sleep(0.002)  # stay well within the socket pair's buffer
    expected_model = PathModel(imp, seed=1, name="a_to_b")
    expected_lost = {
        seq for seq in range(200) if not isinstance(expected_model.admit(0.0, 4), float)
    }
    reply = wait_until(lambda: _stats_once(h, lambda r: r.stats.a_to_b.received == 200),
                       "the relay to take all 200 datagrams")
    assert reply.stats.a_to_b.dropped_loss == len(expected_lost)
    h.app_b.setblocking(False)
    got = set()
    while True:
        try:
            got.add(struct.unpack("!I", h.app_b.recv(100))[0])
        except BlockingIOError:
            break
    assert got == set(range(200)) - expected_lost


def test_set_impairments_applies_to_new_packets(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(), Impairment())
    h.app_a.send(b"fast")
    assert h.app_b.recv(100) == b"fast"
    assert isinstance(
        h.request(control.SetImpairments(a_to_b=Impairment(delay_ms=30.0), b_to_a=Impairment())),
        control.Ok,
    )
    start = time.monotonic()
    h.app_a.send(b"slow")
    assert h.app_b.recv(100) == b"slow"
    assert time.monotonic() - start >= 0.030  # the new delay applies: never early


def test_stop_request_ends_the_loop(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(), Impairment())
    assert isinstance(h.request(control.Stop()), control.Ok)
    h.thread.join(timeout=2.0)
    assert not h.thread.is_alive()


def test_control_eof_ends_the_loop(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(), Impairment())
    h.ctrl.close()
    h.thread.join(timeout=2.0)
    assert not h.thread.is_alive()


def test_deadline_ends_the_loop_even_with_packets_pending(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(delay_ms=10_000.0), Impairment(), lifetime_s=0.3)
    h.app_a.send(b"never delivered")
    h.thread.join(timeout=3.0)
    assert not h.thread.is_alive()


def test_bad_request_gets_a_failed_reply(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(), Impairment())
    h.ctrl.send(b'{"type": "Explode"}')
    reply = control.decode_reply(h.ctrl.recv(control.MAX_MESSAGE_BYTES))
    assert isinstance(reply, control.Failed)
    assert "bad request" in reply.message
    assert h.thread.is_alive()


def test_write_errors_are_counted(make_relay: MakeRelay) -> None:
    h = make_relay(Impairment(), Impairment())
    h.app_b.shutdown(socket.SHUT_RDWR)  # B's "TUN" can no longer take packets
    os.set_blocking(h.app_a.fileno(), True)
    h.app_a.send(b"x")
    reply = wait_until(lambda: _stats_once(h, lambda r: r.stats.a_to_b.received > 0),
                       "the relay to take the datagram")
    stats = reply.stats.a_to_b
    assert stats.received == 1
    assert stats.delivered + stats.write_errors == 1


def test_counters_classify_lateness() -> None:
    counters = DirectionCounters()
    for late_s in (0.0, 50e-6, 500e-6, 2e-3, 20e-3):
        counters.on_received(100)
        counters.on_scheduled()
        counters.on_released(100, late_s, ok=True)
    counters.on_received(100)
    counters.on_dropped(DropReason.LOSS)
    counters.on_received(100)
    counters.on_dropped(DropReason.QUEUE_FULL)
    snap = counters.snapshot()
    assert (snap.late_over_100us, snap.late_over_1ms, snap.late_over_10ms) == (3, 2, 1)
    assert snap.late_max_us == pytest.approx(20_000.0)
    assert snap.late_mean_us == pytest.approx((50 + 500 + 2000 + 20_000) / 5)
    assert (snap.received, snap.delivered, snap.dropped, snap.in_flight) == (7, 5, 2, 0)
