"""The send round's taking of plain channels, CPU ns per round: two source trees, interleaved.

    git worktree add /tmp/rlbridge-base <commit> && (cd /tmp/rlbridge-base && pip install -e .)
    .venv/bin/python benchmarks/send_round_ab.py --a /tmp/rlbridge-base/src --b src \
        [--repeats 10] [--channels 10] [--rounds 20000]

What ``take_plain`` (rlbridge/client/session/plain_round.py) costs the send thread per round,
without a
socket, a server or a second thread: ``--channels`` plain UDP outgoing channels, and per round
the control loop's writes (not timed) then one ``take_plain`` (timed, ``time.thread_time``:
CPU time, robust to the machine's load). Three cases:

* ``one each``: one value per channel since the last round (the common case);
* ``three each``: three values per channel (the drain path, ``take_parts``);
* ``empty``: nothing written (the cost of looking).

A child process per run, with ``PYTHONPATH`` set to tree A or B (ABBA...), so each tree runs
as it is built (compiled or not: each run prints its ``rlbridge._compiled.STATE``). Prints
every run, the medians (ns per round) and B/A. Nothing here asserts: figures belong in
benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

CASES = ("one each", "three each", "empty")


def child(channels: int, rounds: int) -> None:
    """One run in the tree on ``PYTHONPATH``: one JSON line, ns per round per case."""
    from rlbridge._compiled import STATE
    from rlbridge.client.channels.outgoing import OutgoingChannel
    from rlbridge.client.session.plain_round import take_plain
    from rlbridge.csp.bell import SendBell
    from rlbridge.wire.bundle import Part

    bell = SendBell()
    chans = [OutgoingChannel(i, f"/ab/c{i}", "std_msgs/msg/Float64", "data", transport="udp",
                             immediate=False, buffer_size=64, doorbell=bell)
             for i in range(channels)]
    assert all(ch.plain for ch in chans)
    parts: list[Part] = []
    clock = time.thread_time_ns
    ns: dict[str, float] = {}
    for case, per_round in zip(CASES, (1, 3, 0), strict=True):
        spent = 0
        for r in range(rounds):
            value = float(r)
            for ch in chans:
                for _ in range(per_round):
                    ch.write(value)
            start = clock()
            take_plain(chans, parts, 64)
            spent += clock() - start
            parts.clear()
        ns[case] = spent / rounds
    print(json.dumps({"state": STATE, "ns": ns}))


def run_one(tree: str, args: argparse.Namespace) -> tuple[str, dict[str, float]]:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()))
    out = subprocess.run(
        [sys.executable, __file__, "child", "--channels", str(args.channels), "--rounds",
         str(args.rounds)], env=env, capture_output=True, text=True, timeout=300, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    return str(got["state"]), {k: float(v) for k, v in got["ns"].items()}


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("mode", nargs="?", default="ab", choices=("ab", "child"))
    p.add_argument("--channels", type=int, default=10)
    p.add_argument("--rounds", type=int, default=20_000)
    p.add_argument("--a", help="src/ of the baseline tree")
    p.add_argument("--b", help="src/ of the tree under test")
    p.add_argument("--repeats", type=int, default=10)
    args = p.parse_args()
    if args.mode == "child":
        child(args.channels, args.rounds)
        return
    if not (args.a and args.b):
        p.error("--a and --b are required")
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    for i in range(args.repeats):
        for arm in ("AB" if i % 2 == 0 else "BA"):
            state, got = run_one(args.a if arm == "A" else args.b, args)
            runs[arm].append(got)
            print(f"{arm} " + " ".join(f"{k}={got[k]:.0f}" for k in CASES) + f" ({state})",
                  flush=True)
    print(f"\nmedians, CPU ns per take_plain round ({args.repeats} runs each, "
          f"{args.channels} channels, {args.rounds} rounds per case):")
    print(f"{'':12}{'A':>9}{'B':>9}{'B/A':>7}")
    for k in CASES:
        med_a = statistics.median(r[k] for r in runs["A"])
        med_b = statistics.median(r[k] for r in runs["B"])
        print(f"{k:12}{med_a:9.0f}{med_b:9.0f}{med_b / med_a:7.2f}")


if __name__ == "__main__":
    main()
