"""Micro-benchmark of the CSP layer: channels and rings next to deque and queue.Queue.

What is measured, and why that way:

* **Single thread, ns per operation** for each channel kind and the raw rings: ``write``
  (into a buffer big enough to hold every value), ``read`` (draining it), ``write+read``
  (one of each on a small buffer: the steady state of an HRT loop), and the HRT-specific
  paths (an overwriting write into a full buffer, a non-blocking read with nothing new).
  ``collections.deque`` and ``queue.Queue`` doing the same operations in the same run are
  the baselines; every figure includes the same ``for`` loop and bound-method call, so
  the ratios compare like with like (the loop with a Python no-op call is reported too).
* **Two threads, ns per value** handed over: a rendezvous ``Channel()`` against
  ``queue.Queue(maxsize=1)``. This is dominated by thread wake-ups (futex, GIL hand-off),
  not by the data structure.
* **Allocation**: tracemalloc's net traced memory after ``N`` and after ``2N`` steady-state
  operations; the difference, per million operations, is what grows. It should be zero for
  the HRT paths (the few counter ints alive at the end are a constant, not growth).

Each case is set up afresh for every repeat, cases are interleaved across repeats to
spread machine noise over all of them, and the median is reported.
"""

from __future__ import annotations

import collections
import os
import platform
import queue
import statistics
import sys
import threading
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass

from rlbridge.csp.channel import Channel
from rlbridge.csp.ring import MpscRing, SpscRing

Loop = Callable[[int], None]  # runs an operation n times
Setup = Callable[[int], Loop]  # builds a fresh subject for n operations
VALUE = 1.5  # what every benchmark writes (a float: a typical set point)
_SMALL = 8  # capacity of the buffers used in steady-state rows


@dataclass(frozen=True, slots=True)
class BenchRow:
    """One measured figure. ``ns_per_op`` or ``alloc_growth_per_mop`` is set, not both."""

    subject: str
    operation: str
    ops: int
    repeats: int
    ns_per_op: float | None = None
    vs_deque: float | None = None
    vs_queue: float | None = None
    alloc_growth_per_mop: float | None = None


# -- single-thread cases -----------------------------------------------------------------


def _loop(op: Callable[[float], object]) -> Loop:
    def run(n: int) -> None:
        value = VALUE
        for _ in range(n):
            op(value)

    return run


def _loop0(op: Callable[[], object]) -> Loop:
    def run(n: int) -> None:
        for _ in range(n):
            op()

    return run


def _loop2(put: Callable[[float], object], get: Callable[[], object]) -> Loop:
    def run(n: int) -> None:
        value = VALUE
        for _ in range(n):
            put(value)
            get()

    return run


def _filled(put: Callable[[float], object], n: int) -> None:
    for _ in range(n):
        put(VALUE)


def _cases() -> dict[tuple[str, str], Setup]:
    """(subject, operation) -> setup; operations named alike are compared with each other."""

    def chan(size: int, **kw: object) -> Channel[float]:
        return Channel(size, **kw)  # type: ignore[arg-type]

    nb: dict[str, object] = {"blocking": False, "initial": 0.0}

    def read_filled(make: Callable[[int], Channel[float]]) -> Setup:
        def setup(n: int) -> Loop:
            c = make(n)
            c.deliver_many([VALUE] * n)
            return _loop0(c.read)

        return setup

    def ring_filled(n: int) -> Loop:
        r: SpscRing[float] = SpscRing(n)
        _filled(r.push, n)
        return _loop0(r.pop)

    def deque_filled(n: int) -> Loop:
        d: collections.deque[float] = collections.deque([VALUE] * n)
        return _loop0(d.popleft)

    def queue_filled(n: int) -> Loop:
        q: queue.Queue[float] = queue.Queue()
        _filled(q.put_nowait, n)
        return _loop0(q.get_nowait)

    def stale(n: int) -> Loop:
        c = chan(_SMALL, **nb)
        c.write(VALUE)
        c.read()
        return _loop0(c.read)

    def small(**kw: object) -> Setup:
        return lambda n: _loop2(*_ends(chan(_SMALL, **kw)))

    def mpsc_drain(n: int) -> Loop:
        r: MpscRing[float] = MpscRing(n)
        _filled(r.push, n)
        out: list[float] = []

        def run(k: int) -> None:
            r.drain_into(out, k)

        return run

    return {
        ("loop + Python no-op call", "(overhead)"): lambda n: _loop(lambda v: None),
        ("collections.deque", "write"): lambda n: _loop(collections.deque[float]().append),
        ("collections.deque", "read"): deque_filled,
        ("collections.deque", "write+read"): lambda n: _loop2(
            *_deque_ends(collections.deque(maxlen=_SMALL))
        ),
        ("collections.deque", "write (overwriting)"): lambda n: _loop(
            collections.deque([VALUE] * _SMALL, maxlen=_SMALL).append
        ),
        ("queue.Queue", "write"): lambda n: _loop(queue.Queue[float]().put_nowait),
        ("queue.Queue", "read"): queue_filled,
        ("queue.Queue", "write+read"): lambda n: _loop2(*_queue_ends(queue.Queue(_SMALL))),
        ("SpscRing", "write"): lambda n: _loop(SpscRing[float](n).push),
        ("SpscRing", "read"): ring_filled,
        ("SpscRing", "write+read"): lambda n: _loop2(*_ring_ends(SpscRing[float](_SMALL))),
        ("SpscRing", "write (overwriting)"): lambda n: _loop(
            _full(SpscRing[float](_SMALL)).push_overwrite
        ),
        ("MpscRing (lane lookup)", "write"): lambda n: _loop(MpscRing[float](n).push),
        ("MpscRing", "read (batch drain)"): mpsc_drain,
        ("Channel(n) blocking", "write"): lambda n: _loop(chan(n).write),
        ("Channel(n) blocking", "read"): read_filled(chan),
        ("Channel(8) blocking", "write+read"): small(),
        ("Channel(8) blocking", "write (overwriting)"): lambda n: _loop(_full_chan(chan(_SMALL))),
        ("Channel(n) non-blocking", "write"): lambda n: _loop(chan(n, **nb).write),
        ("Channel(n) non-blocking", "read"): read_filled(lambda n: chan(n, **nb)),
        ("Channel(8) non-blocking", "write+read"): small(**nb),
        ("Channel(8) non-blocking", "read (nothing new)"): stale,
    }


def _ends(c: Channel[float]) -> tuple[Callable[[float], object], Callable[[], object]]:
    return c.write, c.read


def _deque_ends(
    d: collections.deque[float],
) -> tuple[Callable[[float], object], Callable[[], object]]:
    return d.append, d.popleft


def _queue_ends(q: queue.Queue[float]) -> tuple[Callable[[float], object], Callable[[], object]]:
    return q.put_nowait, q.get_nowait


def _ring_ends(r: SpscRing[float]) -> tuple[Callable[[float], object], Callable[[], object]]:
    return r.push, r.pop


def _full(r: SpscRing[float]) -> SpscRing[float]:
    _filled(r.push, r.capacity)
    return r


def _full_chan(c: Channel[float]) -> Callable[[float], None]:
    _filled(c.write, _SMALL)
    return c.write


# -- two-thread hand-off -------------------------------------------------------------------


def _handoff(put: Callable[[float], object], get: Callable[[], object], n: int) -> float:
    """ns per value for ``n`` values passed from a writer thread to this thread."""
    writer = threading.Thread(target=_loop(put), args=(n,), name="bench-writer")
    start = time.perf_counter_ns()
    writer.start()
    for _ in range(n):
        get()
    writer.join()
    return (time.perf_counter_ns() - start) / n


def _handoff_cases() -> dict[str, Callable[[int], float]]:
    def rendezvous(n: int) -> float:
        c: Channel[float] = Channel()
        return _handoff(c.write, c.read, n)

    def bounded_queue(n: int) -> float:
        q: queue.Queue[float] = queue.Queue(maxsize=1)
        return _handoff(q.put, q.get, n)

    return {"Channel() rendezvous": rendezvous, "queue.Queue(maxsize=1)": bounded_queue}


# -- allocation ----------------------------------------------------------------------------


def _net_growth(setup: Setup, n: int) -> float:
    """Bytes per million operations by which traced memory grows in steady state."""
    loop = setup(3 * n)  # room for warm-up + N + 2N operations where the subject fills up
    loop(n // 2)  # warm-up: counters past the small-int cache, free lists primed
    tracemalloc.start()
    try:
        loop(n)  # absorbs the switch from untraced to traced counter ints
        after_n = tracemalloc.get_traced_memory()[0]
        loop(n)  # anything the operations keep allocating shows up as growth here
        after_2n = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return (after_2n - after_n) * 1e6 / n


_ALLOC_CASES = (
    ("collections.deque", "write+read"),
    ("collections.deque", "write (overwriting)"),
    ("queue.Queue", "write+read"),
    ("SpscRing", "write+read"),
    ("SpscRing", "write (overwriting)"),
    ("Channel(8) blocking", "write+read"),
    ("Channel(8) blocking", "write (overwriting)"),
    ("Channel(8) non-blocking", "write+read"),
    ("Channel(8) non-blocking", "read (nothing new)"),
)


# -- driver and report ---------------------------------------------------------------------


def run_channel_bench(n: int = 200_000, repeats: int = 5) -> list[BenchRow]:
    """Measure everything described in the module docstring; medians over ``repeats``."""
    if n < 1_000 or repeats < 1:
        raise ValueError("use n >= 1000 and repeats >= 1")
    cases = _cases()
    samples: dict[tuple[str, str], list[float]] = {key: [] for key in cases}
    handoffs = _handoff_cases()
    n_handoff = max(500, n // 100)
    hand_samples: dict[str, list[float]] = {key: [] for key in handoffs}
    for _ in range(repeats):
        for key, setup in cases.items():
            loop = setup(n)
            start = time.perf_counter_ns()
            loop(n)
            samples[key].append((time.perf_counter_ns() - start) / n)
        for name, run in handoffs.items():
            hand_samples[name].append(run(n_handoff))

    med = {key: statistics.median(values) for key, values in samples.items()}
    base = {op: (med.get(("collections.deque", op)), med.get(("queue.Queue", op))) for _, op in med}
    rows = [
        BenchRow(subject, op, n, repeats, ns, *(_ratio(ns, b) for b in base[op]))
        for (subject, op), ns in med.items()
    ]
    queue_hand = statistics.median(hand_samples["queue.Queue(maxsize=1)"])
    for name, values in hand_samples.items():
        ns = statistics.median(values)
        rows.append(BenchRow(name, "hand-off between 2 threads", n_handoff, repeats, ns,
                             None, _ratio(ns, queue_hand)))  # fmt: skip
    alloc_n = min(n, 100_000)
    for key in _ALLOC_CASES:
        growth = _net_growth(cases[key], alloc_n)
        rows.append(BenchRow(*key, ops=alloc_n, repeats=1, alloc_growth_per_mop=growth))
    return rows


def _ratio(value: float, baseline: float | None) -> float | None:
    return None if baseline is None or baseline <= 0 else value / baseline


def _num(value: float | None, digits: int = 0) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def format_markdown(rows: list[BenchRow]) -> str:
    """Render the rows as markdown: a header, the timing table, the allocation table."""
    timing = [r for r in rows if r.ns_per_op is not None]
    alloc = [r for r in rows if r.alloc_growth_per_mop is not None]
    n = max((r.ops for r in timing), default=0)
    repeats = max((r.repeats for r in timing), default=0)
    lines = [
        "# CSP layer micro-benchmark",
        "",
        f"Python {platform.python_version()} ({platform.python_implementation()}), "
        f"{platform.system()} {platform.release()}, {platform.machine()}, "
        f"{len(os.sched_getaffinity(0))} CPUs available; switch interval "
        f"{sys.getswitchinterval() * 1e3:g} ms; load average {os.getloadavg()[0]:.1f} when the "
        f"report was written (other processes inflate every row alike). Median of {repeats} "
        f"repeats, {n:,} operations "
        "each (hand-offs: fewer, see the ops column). Every figure includes the loop; the "
        "first row is the loop plus one call of a Python function (deque and Queue methods "
        "are C calls, cheaper than that). Ratios compare against the same operation on the "
        "baseline measured in the same run. A rendezvous hand-off needs two wake-ups per "
        "value (the writer waits until the value is taken), a Queue(maxsize=1) one.",
        "",
        "| subject | operation | ops | ns/op | x deque | x Queue |",
        "|---|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r.subject} | {r.operation} | {r.ops:,} | {_num(r.ns_per_op)} "
        f"| {_num(r.vs_deque, 2)} | {_num(r.vs_queue, 2)} |"
        for r in timing
    ]
    lines += [
        "",
        "Allocation in steady state: growth of tracemalloc's traced memory between N and 2N "
        "operations, in bytes per million operations (0 = nothing accumulates).",
        "",
        "| subject | operation | N | bytes / 1M ops |",
        "|---|---|---:|---:|",
    ]
    lines += [
        f"| {r.subject} | {r.operation} | {r.ops:,} | {_num(r.alloc_growth_per_mop)} |"
        for r in alloc
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.channels [--n N] [--repeats R] [--out FILE]``."""
    import argparse
    import datetime

    parser = argparse.ArgumentParser(prog="python -m benchmarks.channels",
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--n", type=int, default=200_000, help="operations per measurement")
    parser.add_argument("--repeats", type=int, default=5, help="repeats; figures are medians")
    parser.add_argument("--out", default="benchmarks/results/channels.md",
                        help="markdown file the figures are written to")
    args = parser.parse_args(argv)
    text = format_markdown(run_channel_bench(args.n, args.repeats))
    header = "# CSP layer micro-benchmark\n"
    command = "python -m benchmarks.channels " + " ".join(sys.argv[1:] if argv is None else argv)
    stamp = f"\nCommand: `{command.strip()}` ({datetime.date.today().isoformat()}).\n"
    text = text.replace(header, header + stamp, 1) if text.startswith(header) else text
    with open(args.out, "w") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
