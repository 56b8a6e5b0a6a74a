"""A doorbell: lets consumers sleep until a producer signals, producers pay only when one sleeps.

The waiting side of the SDK's hand-offs: a blocked channel reader
(:class:`~rlbridge.csp.channel.Channel`) and the send thread, which sleeps on one doorbell
shared by all its outgoing channels. The protocol (store, then check ``waiting``; register,
then check the state) is in :mod:`rlbridge.csp.channel`'s module docstring.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

__all__ = ["Doorbell"]


class Doorbell:
    """Lets a consumer sleep until a producer signals, without producers taking a lock.

    Producers call :meth:`ring` only when :attr:`waiting` is non-zero; consumers call
    :meth:`wait_for` with a predicate that reads the lock-free state. ``waiting`` is
    written under the lock only and is public so that the check costs one attribute read.

    A waiter parks on a *gate*: a plain ``threading.Lock`` of its own, taken before it is
    listed and released by :meth:`ring`. That is the cheapest wake-up CPython has (one futex
    wake, no re-acquired condition lock on the woken side, all in C), against
    ``threading.Condition``'s Python-level bookkeeping on both sides. Order of a wait:
    register (``waiting``, the gate listed), *then* check the predicate, then block; a ring
    between the check and the block has already released the gate, so nothing is missed.
    """

    __slots__ = ("_gates", "_lock", "waiting")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._gates: list[threading.Lock] = []
        self.waiting = 0

    def ring(self) -> None:
        """Wake every thread blocked in :meth:`wait_for` (a futex wake each: a system call)."""
        with self._lock:
            gates = self._gates
            if gates:
                self._gates = []
                for gate in gates:
                    gate.release()

    def wait_for(self, predicate: Callable[[], object], timeout: float | None = None) -> bool:
        """Block until ``predicate()`` is true or ``timeout`` passes; return its last value."""
        lock = self._lock
        deadline = None if timeout is None else time.monotonic() + timeout
        with lock:
            self.waiting += 1
        try:
            while True:
                gate = _new_lock()
                gate.acquire()
                with lock:
                    self._gates.append(gate)
                if predicate():
                    self._unlist(gate)
                    return True
                if deadline is None:
                    gate.acquire()
                else:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or not gate.acquire(True, remaining):
                        self._unlist(gate)
                        return bool(predicate())
                if predicate():  # rung: the ring took the gate off the list already
                    return True
        finally:
            with lock:
                self.waiting -= 1

    def _unlist(self, gate: threading.Lock) -> None:
        """Take a gate that was not released off the list (a ring may have taken it)."""
        with self._lock:
            if gate in self._gates:
                self._gates.remove(gate)


_new_lock = threading.Lock
