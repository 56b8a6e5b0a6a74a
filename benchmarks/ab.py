"""Two source trees measured in turn (ABBA...), for the ``*_ab.py`` scripts.

A and B alternate, so a change in the machine's load hits both alike; the figure is each side's
median, and B/A next to the load average it was measured under. A script is run as a file
(``python benchmarks/x_ab.py``), so it puts the checkout's root on ``sys.path`` before it
imports this module (:func:`importable`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path


def tree_arguments(parser: argparse.ArgumentParser, repeats: int) -> None:
    """``--a`` and ``--b`` (the trees' src/ directories) and ``--repeats``. Not required by
    argparse: a script's child mode runs without them (the script checks for them)."""
    parser.add_argument("--a", help="src/ directory of the baseline tree")
    parser.add_argument("--b", help="src/ directory of the tree under test")
    parser.add_argument("--repeats", type=int, default=repeats)


def abba(repeats: int) -> Iterator[str]:
    """``"A"``, ``"B"``, ``"B"``, ``"A"``, ...: ``repeats`` runs of each, in alternating order."""
    for i in range(repeats):
        yield from ("A", "B") if i % 2 == 0 else ("B", "A")


@contextlib.contextmanager
def served(*options: str) -> Iterator[int]:
    """``rlbridge serve`` of the installed tree on a free loopback port, with a 5 s watchdog (a
    loaded machine must not end the sessions) and ``options``; yields the port."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = int(sock.getsockname()[1])
    server = subprocess.Popen(
        [str(Path(sys.executable).with_name("rlbridge")), "serve", "--host", "127.0.0.1",
         "--port", str(port), "--timeout-ms", "5000", *options], stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.0)
        yield port
    finally:
        server.terminate()
        server.wait(10)


def interleave(run: Callable[[str], tuple[float, str]], a: str, b: str, repeats: int,
               digits: int, unit: str = "µs/value") -> dict[str, list[float]]:
    """``run`` each tree ``repeats`` times, A and B alternating (ABBA...): every run as it
    ends (its figure in ``unit`` and ``run``'s detail), then the medians and B/A. Returns
    every run's figure per side."""
    results: dict[str, list[float]] = {"A": [], "B": []}
    for name in abba(repeats):
        figure, detail = run(a if name == "A" else b)
        results[name].append(figure)
        print(f"{name} {figure:6.{digits}f} {unit} {detail}", flush=True)
    med = {k: statistics.median(v) for k, v in results.items()}
    for k, v in results.items():
        print(f"{k} median {med[k]:.{digits}f} {unit}  runs {[round(x, digits) for x in v]}")
    print(f"B/A {med['B'] / med['A']:.2f}  load average {os.getloadavg()}")
    return results
