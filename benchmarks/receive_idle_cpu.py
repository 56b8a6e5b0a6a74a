"""The receive thread's CPU by idle strategy and by what the session receives: two trees.

    git worktree add /tmp/rlbridge-base <commit>    # or copy its src/ anywhere
    .venv/bin/python benchmarks/receive_idle_cpu.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 4] [--seconds 3] [--rate 200]

A spinning receive thread (``Bridge.connect(idle=("park", "busy"))``) is worth its core only
when values come in; a publish-only client receives nothing but heartbeats and answers. Each
run is one client process (``PYTHONPATH`` set to tree A or B, in turn: ABBA...) against one
``rlbridge serve`` of the installed tree (a 5 s watchdog, so a loaded machine does not end the
sessions), with three sessions one after the other: publish-only with ``("park", "busy")``,
publish-only with ``"park"`` (the baseline, same run), and ``("park", "busy")`` with a
subscription as well. Each writes a UDP channel at ``--rate`` Hz for ``--seconds``; the figure
is the ``rlbridge-recv`` thread's CPU time (its own CPU-time clock) over the wall time, in % of
one core. Prints every run and the medians per row and tree.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from rlbridge import Tuning

ROWS = (("publish-only, park/busy", ("park", "busy"), False),
        ("publish-only, park", "park", False),
        ("publish + subscribe, park/busy", ("park", "busy"), True))
F64 = "std_msgs/msg/Float64"


def client(port: int, seconds: float, rate: float) -> None:
    """The three sessions (the tree on PYTHONPATH); prints one JSON line of % of a core."""
    from rlbridge.csp.bridge import Bridge

    out: dict[str, float] = {}
    for label, idle, subscribe in ROWS:
        with Bridge.connect("127.0.0.1", port, tuning=Tuning(idle=idle), name="recv-idle",
                            timeout=30) as b:
            pub = b.publish("/recv_idle/out", F64, transport="udp")
            if subscribe:
                b.subscribe("/recv_idle/in", F64, transport="udp")
            thread = next(t for t in threading.enumerate() if t.name == "rlbridge-recv")
            assert thread.ident is not None
            clock = time.pthread_getcpuclockid(thread.ident)
            time.sleep(0.3)
            cpu0, wall0 = time.clock_gettime(clock), time.monotonic()
            for i in range(int(seconds * rate)):
                pub.write(float(i))
                time.sleep(1 / rate)
            out[label] = 100 * (time.clock_gettime(clock) - cpu0) / (time.monotonic() - wall0)
    print(json.dumps(out), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rate", type=float, default=200.0)
    parser.add_argument("--client", type=int, help=argparse.SUPPRESS)  # a run: the port
    if not __package__:  # run as a file: the checkout's root makes `benchmarks` importable
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks.ab import abba, served, tree_arguments

    tree_arguments(parser, repeats=4)
    args = parser.parse_args()
    if args.client:
        client(args.client, args.seconds, args.rate)
        return
    if not args.a or not args.b:
        parser.error("--a and --b are required")
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    with served() as port:
        for arm in abba(args.repeats):
            env = dict(os.environ, PYTHONPATH=str(Path(args.a if arm == "A" else args.b)
                                                  .resolve()))
            got = subprocess.run(
                [sys.executable, __file__, "--client", str(port), "--seconds",
                 str(args.seconds), "--rate", str(args.rate)],
                env=env, capture_output=True, text=True, timeout=120, check=True)
            row: dict[str, float] = json.loads(got.stdout.strip().splitlines()[-1])
            runs[arm].append(row)
            print(arm, "  ".join(f"{k}: {v:5.1f} %" for k, v in row.items()), flush=True)
    for label, _, _ in ROWS:
        med = {arm: statistics.median(r[label] for r in rs) for arm, rs in runs.items()}
        print(f"{label:32s} A {med['A']:5.1f} %  B {med['B']:5.1f} % of a core")
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
