"""What sealing costs end to end: batched throughput and 1 kHz UDP latency, keyed vs plain.

Run: ``.venv/bin/python benchmarks/bench_security.py [--repeats 5] [--seconds 3]``. Prints a
Markdown report (docs/benchmarks.md quotes it). The paths and processes are those of
``rlbridge bench throughput`` and ``rlbridge bench latency`` (publisher SDK process -> server
process -> subscriber SDK process, on loopback); the only difference between the two columns is
``$RLBRIDGE_PSK`` in the environment of all three processes, which the server and the SDK
both read: with it every session is authenticated, its TCP stream travels as ChaCha20-Poly1305
records and its datagrams are sealed (docs/protocol.md section 16). Plain and keyed runs
alternate within each repeat, so both see the same machine load; the report gives medians and
the keyed/plain ratio per row (targets: throughput >= 0.8x, latency p50 within 10 %).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from rlbridge.bench import latency, throughput
from rlbridge.bench.common import BenchError, Link, LoopbackLink
from rlbridge.wire.auth import PSK_ENV


class KeyedLink:
    """``inner`` whose processes all get ``$RLBRIDGE_PSK`` (server and clients alike)."""

    def __init__(self, inner: Link, key_hex: str) -> None:
        self._inner = inner
        self._key = key_hex
        self.name = f"{inner.name} + PSK"

    def address(self, side: Any) -> str:
        return self._inner.address(side)

    def popen(self, side: Any, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        env = dict(kwargs.pop("env", None) or os.environ)
        env[PSK_ENV] = self._key
        return self._inner.popen(side, argv, env=env, **kwargs)


def _plain_link() -> Link:
    link = LoopbackLink()
    os.environ.pop(PSK_ENV, None)  # the plain column must really be plain
    return link


T = TypeVar("T")


def _retrying(run: Callable[[], T], retries: dict[str, int], name: str, tries: int = 3) -> T:
    """``run()``, again after a BenchError (a session's watchdog firing on a loaded machine);
    every retry is counted and reported."""
    for attempt in range(tries):
        try:
            return run()
        except BenchError as exc:
            if attempt == tries - 1:
                raise
            retries[name] += 1
            print(f"  retrying after: {str(exc).splitlines()[0]}", file=sys.stderr)
    raise AssertionError("unreachable")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=3.0, help="per throughput run")
    parser.add_argument("--batch", type=int, default=4096, help="write_many size")
    parser.add_argument("--samples", type=int, default=3000, help="per latency run (1 kHz)")
    args = parser.parse_args()
    plain = _plain_link()
    keyed = KeyedLink(LoopbackLink(), os.urandom(32).hex())
    rows = [c for c in throughput.cases(args.batch) if c.key in ("rlb-tcp-batch",
                                                                  "rlb-udp-batch")]
    lat_case = next(c for c in latency.CASES if c.key == "rlb-udp")
    tput: dict[tuple[str, str], list[float]] = {}
    cpu: dict[tuple[str, str], list[float]] = {}
    p50: dict[str, list[float]] = {}
    p99: dict[str, list[float]] = {}
    retries: dict[str, int] = {"plain": 0, "keyed": 0}
    load_before = os.getloadavg()
    for rep in range(args.repeats):
        for name, link in (("plain", plain), ("keyed", keyed)):
            for case in rows:
                print(f"[{rep + 1}/{args.repeats}] {name} {case.label}", file=sys.stderr)
                m = _retrying(lambda lk=link, c=case: throughput.measure(  # type: ignore[misc]
                    lk, c, count=50_000_000, seconds=args.seconds), retries, name)
                tput.setdefault((case.key, name), []).append(m.rate)
                cpu.setdefault((case.key, name), []).append(m.cpu["total"])
            print(f"[{rep + 1}/{args.repeats}] {name} UDP 1 kHz latency", file=sys.stderr)
            lm = _retrying(lambda lk=link: latency.measure(  # type: ignore[misc]
                lk, lat_case, rate_hz=1000.0, count=args.samples), retries, name)
            p50.setdefault(name, []).append(lm.p50)
            p99.setdefault(name, []).append(lm.p99)
    load_after = os.getloadavg()
    print(f"Command: `{' '.join(['.venv/bin/python', *sys.argv])}`  ")
    print(f"Load average before {load_before[0]:.2f}, after {load_after[0]:.2f}; "
          f"medians of {args.repeats} interleaved repeats; runs repeated after a failure "
          f"(a watchdog timeout under load): plain {retries['plain']}, keyed "
          f"{retries['keyed']}.\n")
    print("| path | plain | keyed (sealed) | keyed / plain |")
    print("|---|---:|---:|---:|")
    for case in rows:
        a = statistics.median(tput[(case.key, "plain")])
        b = statistics.median(tput[(case.key, "keyed")])
        print(f"| {case.label}, values/s | {a:,.0f} | {b:,.0f} | {b / a:.2f} |")
        a = statistics.median(cpu[(case.key, "plain")])
        b = statistics.median(cpu[(case.key, "keyed")])
        print(f"| {case.label}, CPU s per 1M values (3 processes) | {a:.2f} | {b:.2f} | "
              f"{b / a:.2f} |")
    for label, data in (("p50", p50), ("p99", p99)):
        a, b = statistics.median(data["plain"]), statistics.median(data["keyed"])
        print(f"| rlbridge UDP 1 kHz one-way latency {label}, us | {a:.0f} | {b:.0f} | "
              f"{b / a:.2f} |")


if __name__ == "__main__":
    main()
