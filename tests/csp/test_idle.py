"""Idle strategies: what each does with poll and block, and the SDK threads running on them."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TypeVar

import pytest
from pattern_support import wait_until

from rlbridge import Tuning
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.idle import BusySpin, Park, SpinThenPark, idle_pair, idle_strategy
from rlbridge.server import ServerThread

T = TypeVar("T")


class Counting:
    """A poll that finds work after ``after`` calls, and a block that records its timeout."""

    def __init__(self, after: int) -> None:
        self.after = after
        self.polls = 0
        self.blocked: list[float | None] = []

    def poll(self) -> str:
        self.polls += 1
        return "work" if self.polls > self.after else ""

    def block(self, timeout: float | None) -> str:
        self.blocked.append(timeout)
        return "parked"


def test_park_blocks_at_once() -> None:
    c = Counting(after=0)
    assert Park().idle(c.poll, c.block, 1.0) == "parked"
    assert c.polls == 0
    assert c.blocked == [1.0]


def test_spin_then_park_returns_work_found_while_spinning() -> None:
    c = Counting(after=50)
    assert SpinThenPark(spin_us=1e6, yield_us=0).idle(c.poll, c.block, None) == "work"
    assert c.blocked == []


def test_spin_then_park_parks_after_its_window_with_the_time_left() -> None:
    c = Counting(after=10**9)
    assert SpinThenPark(spin_us=0, yield_us=0).idle(c.poll, c.block, 5.0) == "parked"
    assert len(c.blocked) == 1
    assert c.blocked[0] is not None
    assert 0 < c.blocked[0] <= 5.0


def test_busy_spin_never_blocks_and_honours_the_timeout() -> None:
    c = Counting(after=10**9)
    assert BusySpin().idle(c.poll, c.block, 0.001) == ""
    assert c.blocked == []
    assert c.polls > 1


@pytest.mark.parametrize("name", ["park", "spin", "busy"])
def test_names_and_pairs(name: str) -> None:
    assert idle_strategy(name).name == name
    send, receive = idle_pair((name, "park"))
    assert (send.name, receive.name) == (name, "park")
    with pytest.raises(ValueError, match="unknown idle strategy"):
        idle_strategy("nap")
    with pytest.raises(TypeError, match="not an idle strategy"):
        idle_strategy(42)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="spin_us"):
        SpinThenPark(spin_us=-1)


@pytest.mark.parametrize("idle", ["spin", "busy", ("busy", "spin")])
def test_bridge_threads_move_values_on_every_strategy(
        server: ServerThread, idle: str | tuple[str, str]) -> None:
    with Bridge.connect("127.0.0.1", server.port, tuning=Tuning(idle=idle), name="idle") as b:
        inbox = b.subscribe("/idle", "std_msgs/msg/Int64", transport="tcp", blocking=True,
                            buffer_size=64)
        out = b.publish("/idle", "std_msgs/msg/Int64", transport="udp")
        for i in range(20):
            out.write(i)
            assert inbox.read(timeout=10.0) == i


def test_busy_spin_yields_the_cpu_between_polls(monkeypatch: pytest.MonkeyPatch) -> None:
    yields: list[int] = []
    monkeypatch.setattr("os.sched_yield", lambda: yields.append(1))
    c = Counting(after=5)
    assert BusySpin().idle(c.poll, c.block, None) == "work"
    assert len(yields) == 5  # one after every poll that found nothing: the GIL goes too


def test_bridge_blocking_reads_wait_by_the_receive_strategy(server: ServerThread) -> None:
    with Bridge.connect("127.0.0.1", server.port, tuning=Tuning(idle=("park", "busy")),
                        name="rd") as b:
        inbox = b.subscribe("/idle_rd", "std_msgs/msg/Int64", transport="udp", blocking=True,
                            buffer_size=64)
        assert inbox.read_idle.name == "busy"


class Recording:
    """A receive-thread strategy that parks, counting the waits the thread asks it for."""

    name = "recording"

    def __init__(self) -> None:
        self.waits = 0

    def idle(self, poll: Callable[[], T], block: Callable[[float | None], T],
             timeout: float | None) -> T:
        self.waits += 1
        return block(timeout)


def _heartbeats_heard(b: Bridge) -> int:
    """Server heartbeats the receive thread has handled: each one is a wake-up of it."""
    link = b._conn.link
    assert link is not None
    return link.stats(time.monotonic_ns()).heartbeats_received


def _after_heartbeats(b: Bridge, n: int) -> None:
    """Wait until the receive thread has woken for ``n`` more heartbeats (100 ms apart)."""
    target = _heartbeats_heard(b) + n
    wait_until(lambda: _heartbeats_heard(b) >= target, f"{n} heartbeats are handled")


def test_a_spinning_receive_strategy_applies_only_while_something_comes_in(
        server: ServerThread) -> None:
    """A publish-only session has only heartbeats and answers to receive: its receive thread
    parks whatever its strategy; a subscription or a provided service brings the strategy in,
    and unsubscribing parks the thread again."""
    recording = Recording()
    with Bridge.connect("127.0.0.1", server.port, tuning=Tuning(idle=("park", recording)),
                        name="rx") as b:
        out = b.publish("/idle_rx_out", "std_msgs/msg/Int64", transport="udp")
        out.write(1)
        _after_heartbeats(b, 3)
        assert recording.waits == 0  # woke for every heartbeat, never asked the strategy

        inbox = b.subscribe("/idle_rx_in", "std_msgs/msg/Int64", transport="udp")
        wait_until(lambda: recording.waits > 0, "the receive thread waits by its strategy")
        b.unsubscribe(inbox)
        _after_heartbeats(b, 2)  # the wait decided before the close is over
        parked = recording.waits
        _after_heartbeats(b, 3)
        assert recording.waits == parked

        requests = b.serve_service("/idle_rx_srv", "std_srvs/srv/Trigger")
        wait_until(lambda: recording.waits > parked, "a provided service brings it back")
        requests.close()


def test_a_service_call_in_flight_brings_the_spinning_strategy_in(server: ServerThread) -> None:
    """A publish-only client that calls a service waits for the answer: while the call is in
    flight its receive thread waits by its strategy, and parks again once the call is over."""
    recording = Recording()
    with (Bridge.connect("127.0.0.1", server.port, name="provider") as provider,
          Bridge.connect("127.0.0.1", server.port, tuning=Tuning(idle=("park", recording)),
                         name="caller") as b):
        requests = provider.serve_service("/idle_rx_call", "std_srvs/srv/Trigger")
        answers: list[dict[str, object]] = []
        caller = threading.Thread(target=lambda: answers.append(
            b.call("/idle_rx_call", "std_srvs/srv/Trigger", timeout=20.0)))
        _after_heartbeats(b, 2)
        assert recording.waits == 0
        caller.start()
        request = requests.read(timeout=20.0)
        wait_until(lambda: recording.waits > 0, "the receive thread waits by its strategy")
        request.reply({"success": True, "message": "ok"})
        caller.join(20.0)
        assert answers == [{"success": True, "message": "ok"}]
        _after_heartbeats(b, 2)
        parked = recording.waits
        _after_heartbeats(b, 3)
        assert recording.waits == parked
