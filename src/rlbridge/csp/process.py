"""CSP process constructs of the thesis (figure 2.4), mapped onto threads.

* :class:`Code` wraps a plain callable (a leaf; any callable is accepted where a process
  is expected and wrapped automatically);
* :class:`Sequential` runs its children one after another in the calling thread;
* :class:`Parallel` runs each child in its own thread and waits for all of them;
* :class:`PriParallel` does the same and gives the children descending OS priorities
  (first child highest): ``SCHED_FIFO``/``SCHED_RR`` where permitted, otherwise
  increasing nice values, and says which in exactly one log line or warning;
* :class:`Recursion` runs its child again and again until the run is stopped.

Lifetimes are explicit (the trio lesson): ``run()`` executes in the calling thread and
returns when done; ``start()`` creates one owner thread, ``stop()`` sets the run's stop
:class:`threading.Event` and ``join(timeout)`` waits for the owner thread, re-raising the
process's error. Every thread is started and joined by the construct that created it.
Stopping is cooperative: composites check the event between children and iterations; a
process blocked in a channel read wakes only when that channel is closed, so the owner
of the channels closes them when it stops the processes.

Failures follow nursery semantics: a child's exception sets the stop event (its
siblings wind down), and the parallel construct raises an :class:`ExceptionGroup` of
all its children's exceptions once every child thread has been joined.

A process can be marked hard real-time (``hrt=True``; inherited by its descendants).
The leaf that is running publishes ``ProcessInfo(name, hrt)`` in a thread-local, so a
channel can tell that an HRT process is about to block on it (:func:`current_process`).
"""

from __future__ import annotations

import errno
import logging
import os
import threading
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, TypeAlias

from rlbridge._compat import BaseExceptionGroup
from rlbridge.errors import RealTimeWarning

_log = logging.getLogger(__name__)

# Per-thread "which leaf process runs here"; written only by Code.execute, which always
# restores the previous value, so nothing outlives the call that set it.
_THREAD_STATE = threading.local()


@dataclass(frozen=True, slots=True)
class ProcessInfo:
    """What a channel learns about the process calling it."""

    name: str
    hrt: bool


def current_process() -> ProcessInfo | None:
    """The leaf process running on the calling thread, if it runs under a process."""
    info: ProcessInfo | None = getattr(_THREAD_STATE, "process", None)
    return info


@dataclass(frozen=True, slots=True)
class RunScope:
    """What a composite hands to its children: the run's stop event and the HRT mark."""

    stop: threading.Event
    hrt: bool = False

    def marked(self, hrt: bool) -> RunScope:
        """This scope, hard real-time if it already was or ``hrt`` is true."""
        return self if self.hrt or not hrt else RunScope(self.stop, True)


class Process(ABC):
    """Base of every process: the run/start/stop/join lifetime around :meth:`execute`."""

    def __init__(self, *, name: str | None = None, hrt: bool = False) -> None:
        self.name = name if name is not None else type(self).__name__
        self.hrt = hrt
        self._lifetime = threading.Lock()
        self._stop_event: threading.Event | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @abstractmethod
    def execute(self, scope: RunScope) -> None:
        """Run once in the calling thread; called by composites and by the lifetime API."""

    def run(self) -> None:
        """Execute in the calling thread until done (or stopped); re-raise its error."""
        stop = self._begin()
        try:
            self.execute(RunScope(stop))
        finally:
            self._end()

    def start(self) -> None:
        """Execute in a new owner thread; pair with :meth:`stop` and :meth:`join`."""
        stop = self._begin()
        thread = threading.Thread(target=self._owner_main, args=(stop,), name=f"csp:{self.name}")
        self._thread = thread
        thread.start()

    def stop(self) -> None:
        """Ask the run to finish: sets its stop event (no effect when not running)."""
        event = self._stop_event
        if event is not None:
            event.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for a started run; return ``False`` on timeout, re-raise its error."""
        thread = self._thread
        if thread is None:
            raise RuntimeError(f"process {self.name!r} was not started")
        thread.join(timeout)
        if thread.is_alive():
            return False
        self._thread = None
        error, self._error = self._error, None
        self._end()
        if error is not None:
            raise error
        return True

    def _owner_main(self, stop: threading.Event) -> None:
        try:
            self.execute(RunScope(stop))
        except BaseException as exc:  # handed to join(), which re-raises it
            self._error = exc

    def _begin(self) -> threading.Event:
        with self._lifetime:
            if self._stop_event is not None:
                raise RuntimeError(f"process {self.name!r} is already running")
            self._stop_event = threading.Event()
            return self._stop_event

    def _end(self) -> None:
        with self._lifetime:
            self._stop_event = None

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}{' hrt' if self.hrt else ''}>"


ProcessLike: TypeAlias = Process | Callable[[], object]


def as_process(proc: ProcessLike) -> Process:
    """Return ``proc`` itself, or a :class:`Code` leaf wrapping a plain callable."""
    return proc if isinstance(proc, Process) else Code(proc)


class Code(Process):
    """A leaf: calls ``fn()`` once per execution (a TERRA code block)."""

    def __init__(self, fn: Callable[[], object], *, name: str | None = None, hrt: bool = False):
        super().__init__(
            name=name if name is not None else getattr(fn, "__name__", repr(fn)), hrt=hrt
        )
        self._fn = fn
        self._infos = (ProcessInfo(self.name, hrt), ProcessInfo(self.name, True))

    def execute(self, scope: RunScope) -> None:
        state = _THREAD_STATE
        previous = getattr(state, "process", None)
        state.process = self._infos[scope.hrt]
        try:
            self._fn()
        finally:
            state.process = previous


class Sequential(Process):
    """Run the children one after another in the calling thread."""

    def __init__(self, *procs: ProcessLike, name: str | None = None, hrt: bool = False) -> None:
        super().__init__(name=name, hrt=hrt)
        self.children: tuple[Process, ...] = tuple(as_process(p) for p in procs)

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        stop = scope.stop
        for child in self.children:
            if stop.is_set():
                return
            child.execute(inner)


class Recursion(Process):
    """Run the child again and again until the run's stop event is set."""

    def __init__(self, proc: ProcessLike, *, name: str | None = None, hrt: bool = False) -> None:
        super().__init__(name=name, hrt=hrt)
        self.child = as_process(proc)

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        stop = scope.stop
        child = self.child
        while not stop.is_set():
            child.execute(inner)


class Scheduler(Protocol):
    """The OS calls used to place threads; a parameter so that tests can refuse them."""

    def set_realtime(self, tid: int, policy: int, priority: int) -> None: ...
    def get_nice(self, tid: int) -> int: ...
    def set_nice(self, tid: int, nice: int) -> None: ...
    def set_affinity(self, tid: int, cpus: Collection[int]) -> None: ...


class OsScheduler:
    """The real thing: per-thread calls on Linux (a TID where POSIX says PID)."""

    def set_realtime(self, tid: int, policy: int, priority: int) -> None:
        if not hasattr(os, "sched_setscheduler"):
            raise OSError(errno.ENOSYS, "os.sched_setscheduler is not available here")
        os.sched_setscheduler(tid, policy, os.sched_param(priority))

    def get_nice(self, tid: int) -> int:
        return os.getpriority(os.PRIO_PROCESS, tid)

    def set_nice(self, tid: int, nice: int) -> None:
        os.setpriority(os.PRIO_PROCESS, tid, nice)

    def set_affinity(self, tid: int, cpus: Collection[int]) -> None:
        if not hasattr(os, "sched_setaffinity"):
            raise OSError(errno.ENOSYS, "os.sched_setaffinity is not available here")
        os.sched_setaffinity(tid, cpus)


CpuSets: TypeAlias = Sequence[Collection[int] | None]


class Parallel(Process):
    """Run each child in its own thread; return when all have finished.

    ``cpus`` optionally pins child ``i`` to the CPU set ``cpus[i]``. Which child runs
    first is up to the OS scheduler, as in the thesis ("a fair chance").
    """

    def __init__(
        self,
        *procs: ProcessLike,
        name: str | None = None,
        hrt: bool = False,
        cpus: CpuSets | None = None,
        scheduler: Scheduler | None = None,
    ) -> None:
        super().__init__(name=name, hrt=hrt)
        self.children: tuple[Process, ...] = tuple(as_process(p) for p in procs)
        if cpus is not None and len(cpus) != len(self.children):
            raise ValueError(f"cpus has {len(cpus)} entries for {len(self.children)} children")
        self._cpus = cpus
        self._scheduler: Scheduler = scheduler if scheduler is not None else OsScheduler()

    def execute(self, scope: RunScope) -> None:
        inner = scope.marked(self.hrt)
        run = _Siblings(len(self.children))
        threads = [
            threading.Thread(
                target=self._child_main,
                args=(rank, child, inner, run),
                name=f"csp:{self.name}/{child.name}",
            )
            for rank, child in enumerate(self.children)
        ]
        try:
            for thread in threads:
                thread.start()
            for event in run.ready:
                event.wait()
            self._placed(run.placements)
            for thread in threads:
                thread.join()
        except BaseException:  # e.g. KeyboardInterrupt in the owner: stop, then join
            scope.stop.set()
            for thread in threads:
                if thread.ident is not None:
                    thread.join()
            raise
        if run.errors:
            raise BaseExceptionGroup(f"{len(run.errors)} process(es) of {self.name!r} failed",
                                     run.errors)  # fmt: skip

    def _child_main(self, rank: int, child: Process, scope: RunScope, run: _Siblings) -> None:
        try:
            try:
                run.placements[rank] = self._place(rank, threading.get_native_id())
            finally:
                run.ready[rank].set()
            child.execute(scope)
        except BaseException as exc:  # collected, re-raised by the owner as a group
            run.errors.append(exc)  # list.append is atomic: no lock needed
            scope.stop.set()

    def _place(self, rank: int, tid: int) -> _Placement | None:
        """Apply per-thread placement in the child thread, before the child runs."""
        cpus = None if self._cpus is None else self._cpus[rank]
        if cpus is not None:
            self._scheduler.set_affinity(tid, cpus)
        return None

    def _placed(self, placements: Sequence[_Placement | None]) -> None:
        """Hook called in the owner once every child thread has been placed."""


@dataclass(frozen=True, slots=True)
class _Placement:
    mechanism: Literal["realtime", "nice", "none"]
    value: int
    reason: str


class _Siblings:
    """What the child threads of one parallel execution share with their owner."""

    __slots__ = ("errors", "placements", "ready")

    def __init__(self, count: int) -> None:
        self.errors: list[BaseException] = []
        self.placements: list[_Placement | None] = [None] * count
        self.ready = [threading.Event() for _ in range(count)]


class PriParallel(Parallel):
    """:class:`Parallel` with descending OS priorities, first child highest.

    Tries ``policy`` (``"fifo"`` or ``"rr"``) with priorities ``top_priority``,
    ``top_priority - 1``, ... for each child thread. Where that is refused (no
    ``CAP_SYS_NICE``, ``RLIMIT_RTPRIO`` 0, not Linux) it falls back to nice values
    ``base, base + 1, ...`` (an unprivileged thread may only lower its priority), and
    says so in one :class:`RealTimeWarning`; success is one INFO log line.
    """

    def __init__(
        self,
        *procs: ProcessLike,
        name: str | None = None,
        hrt: bool = False,
        cpus: CpuSets | None = None,
        policy: Literal["fifo", "rr"] = "fifo",
        top_priority: int = 50,
        scheduler: Scheduler | None = None,
    ) -> None:
        super().__init__(*procs, name=name, hrt=hrt, cpus=cpus, scheduler=scheduler)
        if not 1 <= top_priority <= 99:
            raise ValueError(f"top_priority must be in 1..99, got {top_priority}")
        self._policy_name = policy
        self._policy = os.SCHED_FIFO if policy == "fifo" else os.SCHED_RR
        self._top = top_priority
        self._reported = False

    def _place(self, rank: int, tid: int) -> _Placement:
        super()._place(rank, tid)
        priority = max(1, self._top - rank)
        try:
            self._scheduler.set_realtime(tid, self._policy, priority)
            return _Placement("realtime", priority, "")
        except OSError as exc:
            refused = f"{type(exc).__name__}: {exc}"
        try:
            # A new thread inherits its creator's nice value; only raising it is
            # allowed without privileges, so the first child keeps it.
            nice = min(19, self._scheduler.get_nice(tid) + rank)
            self._scheduler.set_nice(tid, nice)
            return _Placement("nice", nice, refused)
        except OSError as exc:
            return _Placement("none", 0, f"{refused}; setpriority: {exc}")

    def _placed(self, placements: Sequence[_Placement | None]) -> None:
        """Say once per instance (not per Recursion iteration) what was applied."""
        if self._reported:
            return
        self._reported = True
        done = [p for p in placements if p is not None]
        policy = f"SCHED_{self._policy_name.upper()}"
        values = ", ".join(str(p.value) for p in done)
        if all(p.mechanism == "realtime" for p in done):
            _log.info("PriParallel %r: %s priorities %s applied", self.name, policy, values)
            return
        reason = next(p.reason for p in done if p.mechanism != "realtime")
        if all(p.mechanism == "nice" for p in done):
            used = f"using nice values {values} instead (higher = less CPU)"
        else:
            used = "per child: " + ", ".join(f"{p.mechanism} {p.value}" for p in done)
        warnings.warn(
            RealTimeWarning(
                f"PriParallel {self.name!r}: {policy} refused ({reason}; it needs "
                f"CAP_SYS_NICE or RLIMIT_RTPRIO >= {self._top}); {used}"
            ),
            stacklevel=2,
        )
