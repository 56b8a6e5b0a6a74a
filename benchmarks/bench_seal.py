"""Per-datagram cost of sealing (counter + AEAD) next to plain datagrams, in the same run.

Run: ``.venv/bin/python benchmarks/bench_seal.py [--repeats 7] [--number 20000]``. Prints a
Markdown table (docs/security.md quotes it): median nanoseconds per datagram over interleaved
repeats, for encode and decode of a one-value datagram and of a full ~1400-byte batch, plain vs
sealed with ChaCha20-Poly1305 (what the protocol uses), and the AEAD alone for
ChaCha20-Poly1305 and AES-256-GCM (the alternative considered).
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time
import timeit
from collections.abc import Callable

from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305

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
    nonce, aad = bytes(12), msg[:12]
    chacha, gcm = ChaCha20Poly1305(key_a), AESGCM(key_a)
    out["AEAD only, 1 value: AES-256-GCM vs ChaCha20-Poly1305"] = (
        lambda: gcm.encrypt(nonce, msg, aad),
        lambda: chacha.encrypt(nonce, msg, aad),
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
    parser.add_argument("--cold", type=int, default=500, help="samples of the cold-cache row")
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
    a_cold, b_cold = cold_hop(args.cold)
    print(f"| one hop at 1 kHz, caches cold (encode + decode, 1 value; median of {args.cold}) "
          f"| {a_cold:.0f} | {b_cold:.0f} | {b_cold - a_cold:+.0f} | {b_cold / a_cold:.2f} |")
    load = os.getloadavg()
    print(f"\nload average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


def cold_hop(samples: int) -> tuple[float, float]:
    """Median ns of one datagram's encode + decode, plain and sealed, as a 1 kHz stream meets
    them: 1 ms apart, with 8 MiB of other memory touched in between (the tight loops above
    run with every cache warm, which a control stream's datagrams never find)."""
    key_a, key_b = os.urandom(32), os.urandom(32)
    plain, sender, receiver = PacketCodec(), SealedCodec(key_a, key_b), SealedCodec(key_b, key_a)
    other = [bytearray(1 << 20) for _ in range(8)]
    times: dict[str, list[int]] = {"plain": [], "sealed": []}
    for i in range(samples):
        for name, samples_of in times.items():  # interleaved
            for block in other:
                block[::4096] = b"\x01" * 256
            time.sleep(0.001)
            packet = Value(1, i, i, 1.5)
            start = time.perf_counter_ns()
            if name == "plain":
                plain.decode_datagram(plain.encode_datagram(packet, 7))
            else:
                receiver.decode_datagram(sender.encode_datagram(packet, 7))
            samples_of.append(time.perf_counter_ns() - start)
    return statistics.median(times["plain"]), statistics.median(times["sealed"])


if __name__ == "__main__":
    main()
