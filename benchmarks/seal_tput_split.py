"""Batched UDP throughput keyed vs plain, UDP row only, CPU per value split by process.

Run: ``.venv/bin/python benchmarks/seal_tput_split.py [--repeats 7] [--seconds 2]
[--baseline TREE/src] [--noop]``. The ``rlbridge UDP, write_many(4096)`` row of
``bench_security.py`` alone (the same links, the same ``throughput.measure``), quicker than the
whole report: columns plain, keyed, optionally keyed from another tree (``--baseline``) and
keyed with ``bench_security.py``'s no-op cipher stand-in (``--noop``: everything sealing adds
except the cipher call, a measurement only), interleaved in a new random order every repeat.
Prints medians per column (values/s and CPU s per 1M values of the publisher, the server, the
subscriber and all three) and, per column, the median over the repeats of that repeat's ratio
to plain (like load against like load). The server sets the rate: the publisher is not paced
by it, so what it sends beyond is lost at hop 1 (docs/benchmarks.md, cost of encryption).
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import sys

from rlbridge.bench import throughput
from rlbridge.bench.common import Link, LoopbackLink


def main() -> None:
    if not __package__:  # run as a file: the checkout's root makes `benchmarks` importable
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from benchmarks.bench_security import (
        _NOOP_CIPHER_CHILD,
        _PROCESSES,
        KeyedLink,
        SwappedCipherLink,
        TreeLink,
        _plain_link,
    )

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seconds", type=float, default=2.0, help="per run")
    parser.add_argument("--batch", type=int, default=4096, help="write_many size")
    parser.add_argument("--baseline", metavar="TREE/src",
                        help="add a keyed column whose processes import rlbridge from there")
    parser.add_argument("--noop", action="store_true",
                        help="add a keyed column with the cipher replaced by a no-op")
    parser.add_argument("--seed", type=int, default=None)
    args = parser.parse_args()
    case = {c.key: c for c in throughput.cases(args.batch)}["rlb-udp-batch"]
    links: dict[str, Link] = {"plain": _plain_link(),
                              "keyed": KeyedLink(LoopbackLink(), os.urandom(32).hex())}
    if args.baseline:
        links["baseline"] = TreeLink(LoopbackLink(), os.urandom(32).hex(), args.baseline)
    if args.noop:
        links["noop-cipher"] = SwappedCipherLink(LoopbackLink(), os.urandom(32).hex(),
                                                 _NOOP_CIPHER_CHILD, "no-op cipher")
    seed = random.randrange(1 << 32) if args.seed is None else args.seed
    order = random.Random(seed)
    runs: dict[str, list[throughput.Measurement]] = {name: [] for name in links}
    load_before = os.getloadavg()[0]
    for rep in range(args.repeats):
        names = list(links)
        order.shuffle(names)
        for name in names:
            m = throughput.measure(links[name], case, count=50_000_000, seconds=args.seconds)
            runs[name].append(m)
            print(f"[{rep + 1}/{args.repeats}] {name}: {m.rate:,.0f} values/s, CPU "
                  + ", ".join(f"{k} {v:.3f}" for k, v in m.cpu.items()), file=sys.stderr)
    load_after = os.getloadavg()[0]
    med = statistics.median
    print(f"Command: `{' '.join(['.venv/bin/python', *sys.argv])}`  ")
    print(f"Load average before {load_before:.2f}, after {load_after:.2f}; medians of "
          f"{args.repeats} interleaved repeats (--seed {seed}); paired: median of the "
          "per-repeat ratios to plain.\n")
    keys = ("total", *_PROCESSES)
    print("| column | values/s | paired | " + " | ".join(f"CPU {k}" for k in keys)
          + " | paired CPU total |")
    print("|---|---:|---:|" + "---:|" * len(keys) + "---:|")
    plain = runs["plain"]
    for name, ms in runs.items():
        rate = med(m.rate for m in ms)
        paired = med(m.rate / p.rate for m, p in zip(ms, plain, strict=True))
        cpu = " | ".join(f"{med(m.cpu[k] for m in ms):.3f}" for k in keys)
        paired_cpu = med(m.cpu["total"] / p.cpu["total"] for m, p in zip(ms, plain, strict=True))
        print(f"| {name} | {rate:,.0f} | {paired:.2f} | {cpu} | {paired_cpu:.2f} |")


if __name__ == "__main__":
    main()
