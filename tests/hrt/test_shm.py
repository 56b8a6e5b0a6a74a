"""The shared-memory link between an HRT loop process and the SDK process (rlbridge.hrt.shm).

Single-process tests pin the semantics (latest value, ring order, full ring, errors, lifetime);
the cross-process tests run a real spawned loop process against this one with both sides
hammering the segment, and one test goes end to end through a live server.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import pytest

from rlbridge.client.bridge import Bridge
from rlbridge.csp.process import Parallel
from rlbridge.hrt.coupling import Ticker
from rlbridge.hrt.shm import HrtProcess, ShmLink, ShmLinkError, forwarder
from rlbridge.server import ServerConfig, ServerThread
from waiting import poll_until, wait_until

F64 = "std_msgs/msg/Float64"
WAIT = 60.0


@pytest.fixture
def link() -> Iterator[ShmLink]:
    with ShmLink.create(inputs=2, outputs=2, capacity=8) as owned:
        yield owned


def test_latest_value_slots(link: ShmLink) -> None:
    assert link.get(0) == 0.0  # before the first put
    link.put(0, 1.5)
    link.put(0, 2.5)
    link.put(1, -1.0)
    assert (link.get(0), link.get(1), link.get(0)) == (2.5, -1.0, 2.5)
    assert link.torn_reads == 0


def test_ring_keeps_order_and_counts_what_a_full_ring_refuses(link: ShmLink) -> None:
    assert all(link.push(0, float(i)) for i in range(8))
    assert not link.push(0, 8.0)
    assert link.dropped(0) == 1
    assert link.drain(0, max_items=3) == [0.0, 1.0, 2.0]
    assert link.push(1, 42.0)  # rings are independent
    assert link.drain(0) == [3.0, 4.0, 5.0, 6.0, 7.0]
    assert link.drain(0) == []
    for i in range(20):  # wraps around several times
        assert link.push(0, float(i))
        assert link.drain(0) == [float(i)]
    assert link.drain(1) == [42.0]
    assert link.dropped(1) == 0


def test_bad_indices_and_layouts_are_clear_errors(link: ShmLink) -> None:
    with pytest.raises(IndexError):
        link.put(2, 0.0)
    with pytest.raises(IndexError):
        link.get(-1)
    with pytest.raises(IndexError):
        link.push(2, 0.0)
    with pytest.raises(ValueError, match="inputs or outputs"):
        ShmLink.create(inputs=0, outputs=0)
    with pytest.raises(ValueError, match="capacity"):
        ShmLink.create(capacity=0)
    with pytest.raises(ValueError, match="needs 2 inputs and 2 outputs"):
        forwarder(link, [], [])


def test_attach_sees_the_owner_and_close_unlinks() -> None:
    owner = ShmLink.create(inputs=1, outputs=1, capacity=4)
    name = owner.name
    try:
        with ShmLink.attach(name) as other:
            assert (other.inputs, other.outputs, other.capacity) == (1, 1, 4)
            assert not other.owner
            owner.put(0, 3.0)
            assert other.get(0) == 3.0
            assert other.push(0, 7.0)
            assert owner.drain(0) == [7.0]
            assert not other.stop_requested
            owner.request_stop()
            assert other.stop_requested
        owner.put(0, 4.0)  # the attached side's close did not unlink
    finally:
        owner.close()
        owner.close()  # idempotent
    with pytest.raises(ShmLinkError, match="no shared memory"):
        ShmLink.attach(name)


def test_attach_refuses_a_foreign_segment() -> None:
    from multiprocessing import shared_memory

    foreign = shared_memory.SharedMemory(create=True, size=4096)
    try:
        with pytest.raises(ShmLinkError, match="not an rlbridge ShmLink"):
            ShmLink.attach(foreign.name)
    finally:
        foreign.close()
        foreign.unlink()


# -- across processes (targets are module-level: the loop process is spawned) --------------------


def _echo_until_stopped(link: ShmLink) -> None:
    """Loop side: push every new input value; spin (never block) until asked to stop."""
    last = -1.0
    while not link.stop_requested:
        value = link.get(0)
        if value != last:
            while not link.push(0, value) and not link.stop_requested:
                pass
            last = value


def _count_to(link: ShmLink, n: int) -> None:
    """Loop side: push 0..n-1 in order, retrying while the ring is full."""
    for i in range(n):
        while not link.push(0, float(i)):
            time.sleep(0)


def test_ring_across_processes_loses_nothing_and_keeps_order() -> None:
    n = 100_000
    with ShmLink.create(inputs=0, outputs=1, capacity=64) as link:
        proc = HrtProcess(link, _count_to, n)
        proc.start()
        got: list[float] = []

        def all_came() -> bool:  # the ring holds 64: drain while the loop pushes
            got.extend(link.drain(0))
            return len(got) >= n

        poll_until(all_came, timeout=WAIT, interval=0)
        assert proc.join(WAIT)
        assert proc.exitcode == 0
        got.extend(link.drain(0))
    assert got == [float(i) for i in range(n)]


def test_latest_value_across_processes_is_never_torn_or_older() -> None:
    with ShmLink.create(inputs=1, outputs=1, capacity=1024) as link:
        proc = HrtProcess(link, _echo_until_stopped)
        proc.start()
        seen: list[float] = []
        try:
            for k in range(1, 100_001):  # each put is a new integer-valued float
                link.put(0, float(k))
                if k % 64 == 0:
                    seen.extend(link.drain(0))

            def last_came() -> bool:
                seen.extend(link.drain(0))
                return bool(seen) and seen[-1] == 100_000.0

            poll_until(last_came, timeout=WAIT, interval=0)
        finally:
            assert proc.stop() == 0
    assert seen
    assert seen[-1] == 100_000.0
    assert all(v.is_integer() and 1 <= v <= 100_000 for v in seen)  # no torn value
    assert all(a < b for a, b in itertools.pairwise(seen))  # never older than before


def _double(link: ShmLink) -> None:
    """Loop side of the end-to-end test: output = 2 * input, at 1 kHz, until stopped."""
    from rlbridge.csp.timer import PeriodicTimer

    timer = PeriodicTimer(0.001, history=1)
    timer.start()
    while not link.stop_requested and timer.wait_next():
        link.push(0, 2.0 * link.get(0))


def test_loop_process_through_a_live_server() -> None:
    with ServerThread(ServerConfig(port=0)) as srv, \
            Bridge.connect("127.0.0.1", srv.port, name="shm-sdk") as sdk, \
            Bridge.connect("127.0.0.1", srv.port, name="shm-peer") as peer, \
            ShmLink.create(inputs=1, outputs=1) as link:
        result = peer.subscribe("/shm/out", F64, blocking=True, buffer_size=64)
        setpoint = peer.publish("/shm/in", F64)
        incoming = sdk.subscribe("/shm/in", F64, blocking=False, initial=0.0)
        out = sdk.publish("/shm/out", F64, through_buffer=True)
        step = forwarder(link, [incoming], [out])

        def pump() -> None:
            step()
            sdk.send()

        pumps = Parallel(Ticker(pump, 200.0, name="shm-pump"))
        with HrtProcess(link, _double):
            pumps.start()
            try:

                def doubled() -> bool:
                    setpoint.write(2.5)
                    return float(result.read(timeout=WAIT)) == 5.0

                wait_until(doubled, "2.5 doubled by the loop process (5.0) through the server",
                           timeout=WAIT, interval=0)
            finally:
                pumps.stop()
                pumps.join(WAIT)
        assert link.dropped(0) == 0


def test_stopping_a_loop_process_that_never_started_is_harmless() -> None:
    with ShmLink.create() as link:
        proc = HrtProcess(link, _echo_until_stopped)
        assert proc.stop() is None
        assert not link.stop_requested
