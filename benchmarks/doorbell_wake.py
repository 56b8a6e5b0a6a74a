"""A blocked reader's wake-up: the doorbell's gate lock against a ``threading.Condition``.

    .venv/bin/python benchmarks/doorbell_wake.py [--repeats 3] [--values 3000]

A writer thread writes into a buffered ``Channel`` whose reader thread is blocked in ``read``
(the writer waits until the reader is registered, then writes ``perf_counter_ns()``); prints,
per doorbell and repeat (interleaved), the p50 of the write with a waiting reader (store plus
ring) and of the wake-up (write to ``read`` returning). ``condition`` is the doorbell before
issue #18 (a ``threading.Condition``), ``gate`` the current ``rlbridge.csp.doorbell.Doorbell``.
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time
from collections.abc import Callable

from rlbridge.csp.channel import Channel
from rlbridge.csp.doorbell import Doorbell


class ConditionBell(Doorbell):
    """The previous doorbell: ``threading.Condition`` on both sides."""

    __slots__ = ("_cond",)

    def __init__(self) -> None:
        super().__init__()
        self._cond = threading.Condition(threading.Lock())

    def ring(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[], object], timeout: float | None = None) -> bool:
        with self._cond:
            self.waiting += 1
            try:
                return bool(self._cond.wait_for(predicate, timeout))
            finally:
                self.waiting -= 1


def once(bell: Doorbell, values: int) -> tuple[float, float]:
    """p50 of write-with-a-waiting-reader and of the wake-up, in microseconds."""
    chan: Channel[int] = Channel(values + 1, doorbell=bell)  # never overwrites
    wake: list[int] = []
    write: list[int] = []

    def reader() -> None:
        for _ in range(values):
            sent = chan.read(timeout=10.0)
            wake.append(time.perf_counter_ns() - sent)

    thread = threading.Thread(target=reader)
    thread.start()
    for _ in range(values):
        time.sleep(0.0003)
        deadline = time.monotonic() + 10.0
        while not bell.waiting and time.monotonic() < deadline:
            time.sleep(0)
        start = time.perf_counter_ns()
        chan.write(start)
        write.append(time.perf_counter_ns() - start)
    thread.join(10.0)
    return statistics.median(write) / 1000, statistics.median(wake) / 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--values", type=int, default=3000)
    args = parser.parse_args()
    for rep in range(args.repeats):
        for name, make in (("condition", ConditionBell), ("gate", Doorbell)):
            w, k = once(make(), args.values)
            print(f"{rep + 1} {name:9s} write with a waiting reader p50 {w:5.1f} us, "
                  f"wake-up p50 {k:5.1f} us")


if __name__ == "__main__":
    main()
