"""Idle strategies: what each does with poll and block, and the SDK threads running on them."""

from __future__ import annotations

import pytest

from rlbridge.csp.bridge import Bridge
from rlbridge.csp.idle import BusySpin, Park, SpinThenPark, idle_pair, idle_strategy
from rlbridge.server import ServerThread


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
    with Bridge.connect("127.0.0.1", server.port, idle=idle, name="idle") as b:
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
    with Bridge.connect("127.0.0.1", server.port, idle=("park", "busy"), name="rd") as b:
        inbox = b.subscribe("/idle_rd", "std_msgs/msg/Int64", transport="udp", blocking=True,
                            buffer_size=64)
        assert inbox.read_idle.name == "busy"
