"""The coupling patterns of thesis chapter 5, end to end through a live server.

These check behaviour, not timing: values arrive, the HRT loop keeps running while nothing
arrives (or, for the naive receive, visibly does not and is reported). Jitter figures are the
benchmark's job (``python -m benchmarks.jitter run``), not a test's: this box may be loaded.
"""

from __future__ import annotations

import itertools
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pattern_support import F64, WAIT, collect, drain, publish_until, wait_until

from rlbridge import Tuning
from rlbridge.csp import patterns
from rlbridge.csp.bridge import Bridge
from rlbridge.csp.bridge_channels import IncomingChannel
from rlbridge.csp.channel import Channel
from rlbridge.csp.gil import shorter_switch_interval
from rlbridge.errors import RealTimeWarning

# PriParallel says once per coupling when the OS refuses real-time priorities (no root).
pytestmark = pytest.mark.filterwarnings("ignore:PriParallel.*:rlbridge.errors.RealTimeWarning")



@pytest.fixture(autouse=True)
def _restore_switch_interval() -> Iterator[None]:
    """Some tests set the process-wide GIL switch interval; undo it per test."""
    before = sys.getswitchinterval()
    yield
    sys.setswitchinterval(before)


class Recorder:
    """A receive control law that remembers what it read (from the HRT thread)."""

    def __init__(self) -> None:
        self.values: list[Any] = []
        self.thread: str | None = None

    def __call__(self, value: Any) -> None:
        self.thread = threading.current_thread().name
        self.values.append(value)

    def saw(self, value: Any) -> Callable[[], bool]:
        return lambda: bool(self.values) and self.values[-1] == value


def counter() -> Callable[[], float]:
    """A send control law: 1.0, 2.0, 3.0, ... one per cycle."""
    numbers = itertools.count(1)
    return lambda: float(next(numbers))


# -- the HRT loop itself ------------------------------------------------------------------------


def test_reference_runs_bounded_cycles_and_records_lateness() -> None:
    coupling = patterns.reference(lambda: None, period=0.002, cycles=50)
    stats = coupling.run()
    assert coupling.released >= 1
    assert stats.cycles == coupling.released
    assert stats.cycles + stats.missed >= 49  # bounded by deadlines, not by releases
    assert len(coupling.loop.lateness_ns()) == stats.cycles
    assert all(late >= 0 for late in coupling.loop.lateness_ns())


def test_control_loop_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="cycles"):
        patterns.ControlLoop(lambda: None, cycles=0)


def test_realtime_switch_interval_sets_and_returns_previous() -> None:
    before = sys.getswitchinterval()
    try:
        assert patterns.realtime_switch_interval(0.0002) == before
        assert sys.getswitchinterval() == pytest.approx(0.0002)
        with pytest.raises(ValueError, match="positive"):
            patterns.realtime_switch_interval(0)
    finally:
        sys.setswitchinterval(before)


def test_bridge_connect_leaves_the_switch_interval_alone_unless_asked(port: int) -> None:
    sys.setswitchinterval(0.005)
    with Bridge.connect("127.0.0.1", port):
        assert sys.getswitchinterval() == pytest.approx(0.005)
    with Bridge.connect("127.0.0.1", port,
                        tuning=Tuning(switch_interval=0.0005)):  # explicit: shortens
        assert sys.getswitchinterval() == pytest.approx(0.0005)
    with Bridge.connect("127.0.0.1", port, tuning=Tuning(switch_interval=0.001)):  # never lengthens
        assert sys.getswitchinterval() == pytest.approx(0.0005)


def test_loop_holds_the_hrt_switch_interval_while_it_runs() -> None:
    sys.setswitchinterval(0.005)
    seen: list[float] = []
    patterns.reference(lambda: seen.append(sys.getswitchinterval()), cycles=5).run()
    assert seen
    assert seen == [pytest.approx(patterns.HRT_SWITCH_INTERVAL)] * len(seen)
    assert sys.getswitchinterval() == pytest.approx(0.005)  # given back afterwards
    seen.clear()
    patterns.reference(lambda: seen.append(sys.getswitchinterval()), cycles=5,
                       switch_interval=None).run()
    assert seen == [pytest.approx(0.005)] * len(seen)


def test_switch_interval_holders_overlap_and_respect_other_changes() -> None:
    sys.setswitchinterval(0.005)
    with shorter_switch_interval(0.001):
        with shorter_switch_interval(0.0002):
            assert sys.getswitchinterval() == pytest.approx(0.0002)
        with shorter_switch_interval(0.002):  # never lengthens
            assert sys.getswitchinterval() == pytest.approx(0.0002)
        assert sys.getswitchinterval() == pytest.approx(0.0002)  # until the last holder ends
    assert sys.getswitchinterval() == pytest.approx(0.005)
    with shorter_switch_interval():
        sys.setswitchinterval(0.003)  # somebody else's choice wins over the restore
    assert sys.getswitchinterval() == pytest.approx(0.003)
    with pytest.raises(ValueError, match="positive"), shorter_switch_interval(0.0):
        pass


def test_bridge_io_priority_is_applied_or_reported(port: int) -> None:
    with Bridge.connect("127.0.0.1", port) as bridge, warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RealTimeWarning)
        applied = bridge.set_io_priority(1)
    if applied:
        assert not w
    else:  # no CAP_SYS_NICE here: refused, and said so once
        assert len(w) == 1
        assert "SCHED_FIFO 1 refused" in str(w[0].message)


def test_bridge_io_priority_refusal_is_a_warning(port: int,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr("os.sched_setscheduler", refuse)
    with Bridge.connect("127.0.0.1", port) as bridge, \
            pytest.warns(RealTimeWarning, match="CAP_SYS_NICE"):
        assert bridge.set_io_priority(40) is False


# -- receive ------------------------------------------------------------------------------------


def test_receive_nonblocking_runs_without_messages_and_sees_new_values(
        ctl: Bridge, peer: Bridge, topic: str) -> None:
    law = Recorder()
    coupling = patterns.receive_nonblocking(ctl, topic, F64, law, initial=-1.0,
                                            layout="thread")
    coupling.start()
    try:
        # nothing is published yet: the loop keeps its timer and reads the initial value
        wait_until(lambda: coupling.released >= 20, "20 releases without a message")
        assert set(law.values) == {-1.0}
        publish_until(peer, topic, 42.0, law.saw(42.0))
        publish_until(peer, topic, 43.0, law.saw(43.0))
    finally:
        coupling.stop()
        assert coupling.join(WAIT)
    assert law.thread is not None
    assert law.thread.endswith("receive-nonblocking:hrt")
    incoming = coupling.channels["in"]
    assert isinstance(incoming, IncomingChannel)
    assert incoming.closed  # the coupling unsubscribed what it subscribed
    assert incoming.statistics().hrt_blocking_reads == 0


def test_receive_blocking_helper_feeds_the_loop(ctl: Bridge, peer: Bridge, topic: str) -> None:
    law = Recorder()
    coupling = patterns.receive_blocking(ctl, topic, F64, law, process=lambda v: 2 * v,
                                         initial=0.0, layout="thread")
    coupling.start()
    try:
        wait_until(lambda: coupling.released >= 20, "20 releases without a message")
        assert set(law.values) == {0.0}
        publish_until(peer, topic, 21.0, law.saw(42.0))  # processed by the helper
    finally:
        coupling.stop()  # the helper is blocked in a read: closing wakes it
        assert coupling.join(WAIT)
    incoming = coupling.channels["in"]
    handoff = coupling.channels["handoff"]
    assert isinstance(incoming, Channel)
    assert isinstance(handoff, Channel)
    # the helper (not the HRT loop) did the blocking reads
    assert incoming.statistics().hrt_blocking_reads == 0
    assert incoming.statistics().read >= 1
    assert handoff.statistics().stale_reads >= 1  # the loop re-read the latest value


def test_receive_naive_blocks_the_loop_and_is_reported(
        ctl: Bridge, peer: Bridge, topic: str) -> None:
    law = Recorder()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RealTimeWarning)
        coupling = patterns.receive_naive(ctl, topic, F64, law)
        coupling.start()
        try:
            # with no message the loop is stuck in its first release
            wait_until(lambda: coupling.released >= 1, "the first release")
            time.sleep(0.05)
            assert law.values == []
            publish_until(peer, topic, 7.0, law.saw(7.0))
        finally:
            coupling.stop()  # wakes the blocked HRT read by closing its channel
            assert coupling.join(WAIT)
    incoming = coupling.channels["in"]
    assert isinstance(incoming, Channel)
    assert incoming.statistics().hrt_blocking_reads >= 1
    messages = [str(w.message) for w in caught if issubclass(w.category, RealTimeWarning)]
    assert any("blocked reading channel" in m for m in messages), messages


# -- send ---------------------------------------------------------------------------------------


def run_send(coupling: patterns.BaseCoupling) -> int:
    """Run a send coupling to its end; return how many values the loop wrote."""
    coupling.run()
    assert coupling.released >= 1
    return coupling.released


def test_send_naive_delivers_every_value(ctl: Bridge, peer: Bridge, topic: str) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    written = run_send(patterns.send_naive(ctl, topic, F64, counter(), transport="tcp",
                                           cycles=200))
    assert collect(sub, written) == [float(i) for i in range(1, written + 1)]


def test_send_buffered_delivers_every_value_in_order(ctl: Bridge, peer: Bridge,
                                                     topic: str) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    coupling = patterns.send_buffered(ctl, topic, F64, counter(), transport="tcp", cycles=200,
                                      buffer_size=256, layout="thread")
    written = run_send(coupling)
    ctl.send(wait=True)
    assert collect(sub, written) == [float(i) for i in range(1, written + 1)]
    handoff = coupling.channels["handoff"]
    assert isinstance(handoff, Channel)
    stats = handoff.statistics()
    assert (stats.overwritten, stats.hrt_blocking_reads) == (0, 0)


def test_send_sampled_sends_a_subsample(ctl: Bridge, peer: Bridge, topic: str) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    written = run_send(patterns.send_sampled(ctl, topic, F64, counter(), rate_hz=50.0,
                                             transport="tcp", cycles=300, layout="thread"))
    got = drain(sub)
    assert got, "no sample arrived"
    assert all(1.0 <= v <= written for v in got)
    assert got == sorted(got)  # latest values, never older than one sent before
    assert len(got) < written


@pytest.mark.parametrize("rate", [100.0, 1000.0])
def test_send_loop_sends_every_value_at_the_sdk_rate(port: int, peer: Bridge, topic: str,
                                                     rate: float) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    with Bridge.connect("127.0.0.1", port, nodelay=True, send_rate_hz=rate) as ctl:
        written = run_send(patterns.send_loop(ctl, topic, F64, counter(), transport="tcp",
                                              cycles=200, layout="thread"))
    # bridge.close() flushed the values the last tick had not sent yet
    assert collect(sub, written) == [float(i) for i in range(1, written + 1)]


def test_send_loop_needs_the_sdk_send_loop(ctl: Bridge, topic: str) -> None:
    with pytest.raises(ValueError, match="send_rate_hz"):
        patterns.send_loop(ctl, topic, F64, counter(), layout="thread")
