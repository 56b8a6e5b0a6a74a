"""Tests of the CSP process constructs and their explicit lifetimes."""

from __future__ import annotations

import errno
import logging
import os
import threading
import warnings
from collections.abc import Collection

import pytest

from rlbridge._compat import ExceptionGroup
from rlbridge.csp.channel import Channel
from rlbridge.csp.process import (
    Code,
    Parallel,
    PriParallel,
    Process,
    ProcessInfo,
    Recursion,
    Sequential,
    as_process,
    current_process,
)
from rlbridge.errors import RealTimeWarning

JOIN = 10.0


def test_sequential_runs_children_in_order_in_the_calling_thread() -> None:
    seen: list[tuple[str, int]] = []
    me = threading.get_ident()
    Sequential(
        lambda: seen.append(("a", threading.get_ident())),
        Code(lambda: seen.append(("b", threading.get_ident()))),
        Sequential(lambda: seen.append(("c", threading.get_ident()))),
    ).run()
    assert seen == [("a", me), ("b", me), ("c", me)]


def test_plain_callables_become_code_leaves() -> None:
    def body() -> None:
        pass

    leaf = as_process(body)
    assert isinstance(leaf, Code)
    assert leaf.name == "body"
    assert as_process(leaf) is leaf


def test_parallel_children_really_run_at_the_same_time() -> None:
    # A rendezvous needs both sides at once: run sequentially, this would time out.
    chan: Channel[int] = Channel()
    got: list[int] = []
    threads: set[int] = set()

    def left() -> None:
        threads.add(threading.get_ident())
        chan.write(1, timeout=JOIN)

    def right() -> None:
        threads.add(threading.get_ident())
        got.append(chan.read(timeout=JOIN))

    Parallel(left, right).run()
    assert got == [1]
    assert len(threads) == 2
    assert threading.get_ident() not in threads


def test_recursion_repeats_until_stopped() -> None:
    count = 0

    def body() -> None:
        nonlocal count
        count += 1
        if count == 5:
            root.stop()

    root = Recursion(body)
    root.run()
    assert count == 5


def test_start_stop_join_lifetime() -> None:
    running = threading.Event()
    root = Recursion(Code(running.set))
    root.start()
    assert running.wait(JOIN)
    with pytest.raises(RuntimeError, match="already running"):
        root.start()
    root.stop()
    assert root.join(JOIN)
    root.start()  # a finished process can run again
    root.stop()
    assert root.join(JOIN)


def test_join_times_out_while_running_and_needs_a_start() -> None:
    gate = threading.Event()
    root = Code(lambda: gate.wait(JOIN))
    with pytest.raises(RuntimeError, match="not started"):
        root.join()
    root.start()
    assert root.join(0.01) is False
    gate.set()
    assert root.join(JOIN) is True


def test_failure_stops_siblings_and_raises_a_group_from_join() -> None:
    spins = 0

    def spin() -> None:
        nonlocal spins
        spins += 1

    def fail() -> None:
        raise ValueError("boom")

    root = Parallel(Recursion(spin), fail, name="pair")
    root.start()
    with pytest.raises(ExceptionGroup, match="pair") as info:
        root.join(JOIN)
    assert [type(e) for e in info.value.exceptions] == [ValueError]
    with pytest.raises(ExceptionGroup):
        Parallel(fail).run()


def test_current_process_and_inherited_hrt_mark() -> None:
    seen: list[ProcessInfo | None] = []
    record = Code(lambda: seen.append(current_process()), name="leaf")
    Sequential(record, Sequential(record, hrt=True), Parallel(record, hrt=True)).run()
    assert seen == [
        ProcessInfo("leaf", hrt=False),
        ProcessInfo("leaf", hrt=True),
        ProcessInfo("leaf", hrt=True),
    ]
    assert current_process() is None  # restored after the leaf


# -- priorities ------------------------------------------------------------------------------


class FakeScheduler:
    """Records what a PriParallel asked for; refuses real-time and/or nice on request."""

    def __init__(self, *, realtime: bool, nice: bool = True) -> None:
        self.allow_realtime = realtime
        self.allow_nice = nice
        self.calls: list[tuple[str, int]] = []
        self.affinity: list[frozenset[int]] = []
        self._lock = threading.Lock()

    def set_realtime(self, tid: int, policy: int, priority: int) -> None:
        if not self.allow_realtime:
            raise PermissionError(errno.EPERM, "Operation not permitted")
        with self._lock:
            self.calls.append(("rt", priority))

    def get_nice(self, tid: int) -> int:
        return 0

    def set_nice(self, tid: int, nice: int) -> None:
        if not self.allow_nice:
            raise PermissionError(errno.EPERM, "Operation not permitted")
        with self._lock:
            self.calls.append(("nice", nice))

    def set_affinity(self, tid: int, cpus: Collection[int]) -> None:
        with self._lock:
            self.affinity.append(frozenset(cpus))


def _three() -> tuple[Process, Process, Process]:
    return Code(lambda: None), Code(lambda: None), Code(lambda: None)


def test_pri_parallel_falls_back_to_nice_with_one_warning() -> None:
    sched = FakeScheduler(realtime=False)
    with pytest.warns(RealTimeWarning) as record:
        PriParallel(*_three(), name="ctl", scheduler=sched).run()
    assert len(record) == 1
    message = str(record[0].message)
    assert "SCHED_FIFO refused (PermissionError" in message
    assert "using nice values 0, 1, 2" in message
    assert sorted(sched.calls) == [("nice", 0), ("nice", 1), ("nice", 2)]


def test_pri_parallel_realtime_is_one_log_line(caplog: pytest.LogCaptureFixture) -> None:
    sched = FakeScheduler(realtime=True)
    with caplog.at_level(logging.INFO, logger="rlbridge.csp.process"), warnings.catch_warnings():
        warnings.simplefilter("error")
        PriParallel(*_three(), name="ctl", policy="rr", top_priority=10, scheduler=sched).run()
    assert [r.getMessage() for r in caplog.records] == [
        "PriParallel 'ctl': SCHED_RR priorities 10, 9, 8 applied"
    ]
    assert sorted(sched.calls) == [("rt", 8), ("rt", 9), ("rt", 10)]


def test_pri_parallel_says_when_nothing_could_be_applied() -> None:
    with pytest.warns(RealTimeWarning, match="per child: none 0, none 0"):
        PriParallel(Code(lambda: None), Code(lambda: None),
                    scheduler=FakeScheduler(realtime=False, nice=False)).run()  # fmt: skip


def test_pri_parallel_warns_once_per_instance_not_per_iteration() -> None:
    count = 0

    def body() -> None:
        nonlocal count
        count += 1
        if count == 6:
            root.stop()

    root = Recursion(PriParallel(body, Code(lambda: None),
                                 scheduler=FakeScheduler(realtime=False)))  # fmt: skip
    with pytest.warns(RealTimeWarning) as record:
        root.run()
    assert count == 6
    assert len(record) == 1


def test_cpu_affinity_is_requested_per_child() -> None:
    sched = FakeScheduler(realtime=True)
    Parallel(*_three(), cpus=[{0}, None, {0, 1}], scheduler=sched).run()
    assert sorted(sched.affinity, key=sorted) == [frozenset({0}), frozenset({0, 1})]
    with pytest.raises(ValueError, match="cpus"):
        Parallel(*_three(), cpus=[{0}])


def test_pri_parallel_on_this_machine_applies_what_it_reports(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Real OS calls: SCHED_FIFO when permitted (root, CAP_SYS_NICE), otherwise nice.
    seen: dict[int, tuple[int, int]] = {}

    def probe(rank: int) -> Code:
        def body() -> None:
            param = os.sched_getparam(0)
            seen[rank] = (os.sched_getscheduler(0), param.sched_priority)

        return Code(body)

    with (
        caplog.at_level(logging.INFO, logger="rlbridge.csp.process"),
        warnings.catch_warnings(record=True) as record,
    ):
        warnings.simplefilter("always")
        PriParallel(probe(0), probe(1), top_priority=5).run()
    messages = [r.getMessage() for r in caplog.records] + [str(w.message) for w in record]
    assert len(messages) == 1
    if "applied" in messages[0]:
        assert seen == {0: (os.SCHED_FIFO, 5), 1: (os.SCHED_FIFO, 4)}
    else:
        assert "nice values" in messages[0] or "per child" in messages[0]
        assert {policy for policy, _ in seen.values()} == {os.SCHED_OTHER}


def test_affinity_on_this_machine() -> None:
    seen: list[set[int]] = []
    Parallel(Code(lambda: seen.append(os.sched_getaffinity(0))), cpus=[{0}]).run()
    assert seen == [{0}]
