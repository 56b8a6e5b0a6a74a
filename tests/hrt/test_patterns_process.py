"""The coupling patterns in their default layout: the HRT loop in its own OS process.

End to end through a live server: values reach the loop process through shared memory, every
value the loop writes reaches a subscriber, and a mistake (a law that cannot cross, a law that
raises, a value that is no number, an unknown layout) is a clear error that leaves nothing
behind (no subscription, no shared-memory segment, no process). Timing is the benchmark's job.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator

import pytest
from pattern_laws import Counter, FailsAt, Recorder, double, not_a_number
from pattern_support import F64, WAIT, collect, drain, wait_until

from proc_children import children, cmdline
from rlbridge.client.bridge import Bridge
from rlbridge.client.channels.incoming import IncomingChannel
from rlbridge.hrt import patterns
from rlbridge.hrt import shm as shm_module
from rlbridge.hrt.isolated import DEFAULT_LAYOUT, IsolatedCoupling
from rlbridge.hrt.shm import ShmLink

pytestmark = [
    pytest.mark.filterwarnings("ignore:PriParallel.*:rlbridge.errors.RealTimeWarning"),
    pytest.mark.skipif(not ShmLink.supported(), reason="the shared-memory link needs x86"),
]


@pytest.fixture(autouse=True)
def no_segment_left() -> Iterator[None]:
    """Every test must leave no segment of its own in /dev/shm: the coupling owns its segment.

    Only the segments this process created count: other processes on the machine (a ROS 2
    test's Fast DDS, another test run) create and remove theirs meanwhile.
    """
    before = set(shm_module._created_here)
    yield
    ours = shm_module._created_here - before
    assert ours.isdisjoint(os.listdir("/dev/shm")), sorted(ours)


def test_the_default_layout_is_the_loops_own_process() -> None:
    assert DEFAULT_LAYOUT == "process"


def publish_while_running(peer: Bridge, topic: str, value: float, coupling: IsolatedCoupling,
                          releases: int = 30) -> None:
    """Publish ``value`` every 10 ms until the SDK process received it, wait until its helper
    put it (or what ``process`` made of it) in the loop's shared-memory slot, then until the
    loop has run ``releases`` more cycles (it reads the slot every cycle).

    The slot is watched, not assumed: the helper is a thread of this (SDK) process and a
    loaded machine can keep it from running while the loop process runs many cycles."""
    out = peer.publish(topic, F64, transport="udp")
    incoming = coupling.channels["in"]
    assert isinstance(incoming, IncomingChannel)
    seen = incoming.statistics().written
    before = coupling.link.get(0)
    wait_until(lambda: incoming.statistics().written != seen, f"{value} to reach the SDK process",
               between=lambda: out.write(value))
    wait_until(lambda: coupling.link.get(0) != before, f"{value} to reach the loop's slot")
    target = coupling.released + releases
    wait_until(lambda: coupling.released >= target, f"{releases} releases after {value}")


def test_receive_nonblocking_feeds_the_loop_process(ctl: Bridge, peer: Bridge,
                                                    topic: str) -> None:
    coupling = patterns.receive_nonblocking(ctl, topic, F64, Recorder(), initial=-1.0)
    assert isinstance(coupling, IsolatedCoupling)
    coupling.start()
    try:
        # the release counter is shared memory: the loop runs with nothing published
        wait_until(lambda: coupling.released >= 20, "20 releases without a message")
        publish_while_running(peer, topic, 42.0, coupling)
        publish_while_running(peer, topic, 43.0, coupling)
    finally:
        coupling.stop()
        assert coupling.join(WAIT)
    law = coupling.final_control
    assert isinstance(law, Recorder)
    assert law.pid not in (None, os.getpid())  # it ran in another process
    assert law.values[0] == -1.0
    assert law.values[-2:] == [42.0, 43.0]
    stats = coupling.stats()
    assert stats.cycles >= coupling.released >= 60
    assert len(coupling.lateness_ns()) == stats.recorded
    assert coupling.loop_info["torn_reads"] == 0
    assert "SCHED" in coupling.loop_info["policy"]  # recorded inside the loop process
    incoming = coupling.channels["in"]
    assert isinstance(incoming, IncomingChannel)
    assert incoming.closed  # the coupling unsubscribed what it subscribed


def test_receive_blocking_processes_in_the_sdk_process(ctl: Bridge, peer: Bridge,
                                                       topic: str) -> None:
    coupling = patterns.receive_blocking(ctl, topic, F64, Recorder(), process=double)
    coupling.start()
    try:
        wait_until(lambda: coupling.released >= 20, "20 releases without a message")
        publish_while_running(peer, topic, 21.0, coupling)
    finally:
        coupling.stop()  # the helper is blocked in a read: closing the channel wakes it
        assert coupling.join(WAIT)
    law = coupling.final_control
    assert law.values == [0.0, 42.0]
    incoming = coupling.channels["in"]
    assert isinstance(incoming, IncomingChannel)
    assert incoming.statistics().hrt_blocking_reads == 0


def test_send_buffered_delivers_every_value_in_order(ctl: Bridge, peer: Bridge,
                                                     topic: str) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    coupling = patterns.send_buffered(ctl, topic, F64, Counter(), transport="tcp", cycles=300)
    coupling.run()
    written = coupling.final_control.k
    assert written == coupling.released >= 1
    assert collect(sub, written) == [float(i) for i in range(1, written + 1)]
    assert coupling.loop_info["ring_dropped"] == 0


def test_send_sampled_sends_a_subsample(ctl: Bridge, peer: Bridge, topic: str) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    coupling = patterns.send_sampled(ctl, topic, F64, Counter(), rate_hz=50.0,
                                     transport="tcp", cycles=300)
    coupling.run()
    written = coupling.final_control.k
    got = drain(sub)
    assert got, "no sample arrived"
    assert all(1.0 <= v <= written for v in got)
    assert got == sorted(got)
    assert len(got) < written


@pytest.mark.parametrize("rate", [100.0, 1000.0])
def test_send_loop_sends_every_value(port: int, peer: Bridge, topic: str, rate: float) -> None:
    sub = peer.subscribe(topic, F64, transport="tcp", blocking=True, buffer_size=4096)
    with Bridge.connect("127.0.0.1", port, nodelay=True, send_rate_hz=rate) as ctl:
        coupling = patterns.send_loop(ctl, topic, F64, Counter(), transport="tcp", cycles=200)
        coupling.run()
    written = coupling.final_control.k  # bridge.close() flushed the last tick's values
    assert collect(sub, written) == [float(i) for i in range(1, written + 1)]


def test_a_law_that_cannot_cross_is_refused_before_anything_is_made(
        ctl: Bridge, topic: str) -> None:
    with pytest.raises(TypeError, match="layout='thread'"):
        patterns.receive_nonblocking(ctl, topic, F64, lambda value: None)
    with pytest.raises(TypeError, match="module-level"):
        patterns.send_buffered(ctl, topic, F64, lambda: 1.0)
    assert ctl.server_stats()["session"]["channels"] == {}  # nothing bound on the server


def test_a_failing_law_is_an_error_with_its_traceback(ctl: Bridge, topic: str) -> None:
    coupling = patterns.send_buffered(ctl, topic, F64, FailsAt(5), cycles=1000)
    with pytest.raises(RuntimeError, match=r"(?s)failed.*ZeroDivisionError.*release 5"):
        coupling.run()
    assert coupling.link.closed


def test_a_value_that_is_no_number_is_an_error(ctl: Bridge, topic: str) -> None:
    coupling = patterns.send_buffered(ctl, topic, F64, not_a_number, cycles=100)
    with pytest.raises(RuntimeError, match="could not convert string to float"):
        coupling.run()


def test_unknown_layout_is_refused(ctl: Bridge, topic: str) -> None:
    with pytest.raises(ValueError, match="layout must be 'process' or 'thread'"):
        patterns.receive_nonblocking(ctl, topic, F64, Recorder(), layout="fork")  # type: ignore[arg-type]


def test_a_killed_loop_process_is_reported(ctl: Bridge, topic: str) -> None:
    coupling = patterns.send_buffered(ctl, topic, F64, Counter())  # runs until stopped
    coupling.start()
    try:
        wait_until(lambda: coupling.released >= 10, "10 releases")
        loops = [pid for pid in children() if "spawn_main" in cmdline(pid)]
        assert len(loops) == 1, "the loop process is not a spawned child of this one"
        os.kill(loops[0], signal.SIGKILL)
        with pytest.raises(RuntimeError, match="without a report"):
            coupling.join(WAIT)
    finally:
        coupling.stop()
    assert coupling.link.closed
    assert [pid for pid in children() if "spawn_main" in cmdline(pid)] == []
