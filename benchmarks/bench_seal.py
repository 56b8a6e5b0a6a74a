"""Per-datagram cost of sealing (counter + MAC) next to plain datagrams, in the same run.

Run: ``.venv/bin/python benchmarks/bench_seal.py [--repeats 7] [--number 20000]``. Prints a
Markdown table (docs/security.md quotes it): median nanoseconds per datagram over interleaved
repeats, for encode and decode of a one-value datagram and of a full ~1400-byte batch, plain vs
sealed with keyed BLAKE2s-128 (what the protocol uses), and the MAC alone for BLAKE2s-128 and
HMAC-SHA256-128 (the alternative considered).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import hmac
import os
import statistics
import timeit
from collections.abc import Callable

from rlbridge.wire import Batch, PacketCodec, Value
from rlbridge.wire.auth import SealedCodec


def cases() -> dict[str, tuple[Callable[[], object], Callable[[], object]]]:
    """``name -> (plain, sealed)`` callables, each handling one datagram."""
    key_a, key_b = os.urandom(32), os.urandom(32)
    plain = PacketCodec()
    sender = SealedCodec(key_a, key_b)
    one = Value(1, 42, 1_700_000_000_000_000_000, 1.2345)
    batch = Batch(1, 42, [1_700_000_000_000_000_000] * 76, [float(i) for i in range(76)])
    out: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {}
    for label, packet in (("1 value", one), ("batch, 76 values", batch)):
        plain_dgram = plain.encode_datagram(packet, 7)
        sealed_dgram = sender.encode_datagram(packet, 7)
        receiver = SealedCodec(key_b, key_a)
        receiver.window = _AlwaysNew()  # type: ignore[assignment]  # one datagram, replayed
        out[f"encode, {label} ({len(plain_dgram)} B plain)"] = (
            functools.partial(plain.encode_datagram, packet, 7),
            functools.partial(sender.encode_datagram, packet, 7),
        )
        out[f"decode, {label}"] = (
            functools.partial(plain.decode_datagram, plain_dgram),
            functools.partial(receiver.decode_datagram, sealed_dgram),
        )
    msg = plain.encode_datagram(one, 7)
    out["MAC only, 1 value: BLAKE2s-128 vs HMAC-SHA256-128"] = (
        lambda: hashlib.blake2s(msg, key=key_a, digest_size=16).digest(),
        lambda: hmac.digest(key_a, msg, "sha256")[:16],
    )
    return out


class _AlwaysNew:
    """A replay window that accepts everything (the benchmark replays one datagram)."""

    def check(self, counter: int) -> bool:
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--number", type=int, default=20000)
    args = parser.parse_args()
    load = os.getloadavg()
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}\n")
    print("| operation | plain ns | sealed ns | extra ns | ratio |")
    print("|---|---:|---:|---:|---:|")
    for name, (plain, sealed) in cases().items():
        a: list[float] = []
        b: list[float] = []
        for _ in range(args.repeats):  # interleaved: both see the same machine load
            a.append(timeit.timeit(plain, number=args.number) / args.number * 1e9)
            b.append(timeit.timeit(sealed, number=args.number) / args.number * 1e9)
        ma, mb = statistics.median(a), statistics.median(b)
        print(f"| {name} | {ma:.0f} | {mb:.0f} | {mb - ma:+.0f} | {mb / ma:.2f} |")
    load = os.getloadavg()
    print(f"\nload average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


if __name__ == "__main__":
    main()
