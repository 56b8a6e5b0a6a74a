"""The send thread's doorbell: one waiter, so one lock that is the gate.

Why not :class:`~rlbridge.csp.doorbell.Doorbell`: that one serves any number of waiters, so
every ring takes its lock and releases each listed waiter's gate, and every wait allocates a
gate, lists it under the lock and takes the lock again to leave: a few Python-level lock
operations per wake-up, paid at every ``Bridge.send()`` by the control loop and again by the
send thread. The send thread is this bell's only waiter, so a binary semaphore does the job: a
``threading.Lock`` that is *held* while no ring is pending. :meth:`SendBell.ring` releases
it (one C call; the futex wake happens only when the thread sleeps on it) and
:meth:`SendBell.wait_for` acquires it, with a timeout.

The protocol is Doorbell's: a producer changes the state the waiter's predicate reads, then
rings if :attr:`SendBell.waiting`; the waiter sets ``waiting`` *before* it checks the
predicate. Under the GIL every thread sees these operations in one order, so one of the two
sees the other: no wake-up is lost. A ring while nobody waits leaves the lock released; the
next wait then returns at once, re-checks the predicate and waits again (one spare check,
never lost or doubled work).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

_monotonic = time.monotonic


class Bell(Protocol):
    """What a producer needs of a doorbell: ring it only while someone ``waiting``."""

    @property
    def waiting(self) -> int: ...

    def ring(self) -> None: ...


class SendBell:
    """A doorbell for exactly one waiting thread (see the module docstring)."""

    __slots__ = ("_lock", "waiting")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # held: no ring pending
        #: Non-zero while the waiter is in (or entering) :meth:`wait_for`.
        self.waiting = 0

    def ring(self) -> None:
        """Wake the waiter, or let its next wait return at once (a futex wake if it sleeps)."""
        try:  # noqa: SIM105 (contextlib.suppress costs two Python calls per ring)
            self._lock.release()
        except RuntimeError:  # already rung and not yet taken: one pending ring is enough
            pass

    def wait_for(self, predicate: Callable[[], object], timeout: float | None = None) -> bool:
        """Block until ``predicate()`` is true or ``timeout`` passes; return its last value."""
        self.waiting += 1  # announced before the predicate reads the state
        try:
            if timeout is None:
                while not predicate():
                    self._lock.acquire()
                return True
            deadline = _monotonic() + timeout
            while not predicate():
                left = deadline - _monotonic()
                if left <= 0:
                    return False
                self._lock.acquire(timeout=left)
            return True
        finally:
            self.waiting -= 1
