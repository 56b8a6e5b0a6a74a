"""Per-datagram cost of sealing (counter + AEAD) next to plain datagrams, in the same run.

Run: ``.venv/bin/python benchmarks/bench_seal.py [--repeats 7] [--number 20000]``. Prints a
Markdown table (docs/security.md and docs/benchmarks.md quote it): median CPU nanoseconds per
datagram (this thread's CPU clock, so waiting for a core under load is not counted) over
interleaved repeats, plain vs sealed with ChaCha20-Poly1305, for the functions each end of the
UDP value path runs per datagram: the sending side's ``DatagramPacker.add`` + ``flush`` (the
SDK's send thread and the server's ``UdpSink`` alike), the server's decode (plain: the body
after the checked header, as ``server/udp.py`` does; sealed: ``decode_datagram``), the SDK
receive thread's ``decode_datagram``; the same for a batch that fills a datagram (70 values,
sealed or not); the replay window's check; the AEAD alone for ChaCha20-Poly1305 and
AES-256-GCM (the alternative considered); and, when ``rlbridge.wire._chacha`` was built, the
AEAD call of libsodium's ChaCha20-Poly1305 against cryptography's, warm and cold (the two
implementations rlbridge.wire.aead chooses between). The sealed rows use this process's
choice (``rlbridge --version``; ``RLBRIDGE_AEAD=cryptography`` for the other).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import os
import statistics
import time
import timeit
from collections.abc import Callable, Iterator

from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305

from rlbridge.wire import Batch, PacketCodec, Value
from rlbridge.wire.aead import IMPLEMENTATIONS, LIBSODIUM
from rlbridge.wire.aead import STATE as AEAD_STATE
from rlbridge.wire.auth import ReplayWindow, SealedCodec
from rlbridge.wire.bundle import DatagramPacker
from rlbridge.wire.codec import DATAGRAM_HEADER, FLAG_BUNDLES
from rlbridge.wire.seal import nonce


def _pack(packer: DatagramPacker, packet: Value | Batch, sent: list[bytes]) -> None:
    """What a send round does with one value packet: add, flush (one datagram)."""
    packer.add(packet)
    packer.flush()
    sent.clear()


def _server_decode(codec: PacketCodec, data: bytes) -> object:
    """server/udp.py's decode of a live session's datagram (header already checked)."""
    if type(codec) is PacketCodec:
        return codec.decode_body(memoryview(data)[DATAGRAM_HEADER.size :])
    return codec.decode_datagram(data)


def _next_decoded(decode: Callable[[bytes], object], datagrams: Iterator[bytes]) -> object:
    """Decode the next datagram: the sealed ones each have their own counter (a replayed one
    is refused), and the plain ones pay the same ``next``."""
    return decode(next(datagrams))


def cases(calls: int) -> dict[str, tuple[Callable[[], object], Callable[[], object]]]:
    """``name -> (plain, sealed)`` callables, each handling one datagram; a sealed decode
    case can be called ``calls`` times (one prebuilt datagram per call)."""
    key_a, key_b = os.urandom(32), os.urandom(32)
    plain = PacketCodec()
    sender = SealedCodec(key_a, key_b)
    one = Value(1, 42, 1_700_000_000_000_000_000, 1.2345)
    batch = Batch(1, 42, [1_700_000_000_000_000_000] * 70, [float(i) for i in range(70)])
    out: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {}
    sent: list[bytes] = []
    plain_packer = DatagramPacker(plain, 7, 1400, sent.append, limit=65507, flags=FLAG_BUNDLES)
    sealed_packer = DatagramPacker(sender, 7, 1400, sent.append, limit=65507,
                                   flags=FLAG_BUNDLES)
    for label, packet in (("1 value", one), ("batch, 70 values", batch)):
        plain_dgram = plain.encode_datagram(packet, 7, FLAG_BUNDLES)
        sealed_dgrams = [sender.encode_datagram(packet, 7, FLAG_BUNDLES) for _ in range(calls)]
        out[f"send: packer add + flush, {label} ({len(plain_dgram)} B plain)"] = (
            functools.partial(_pack, plain_packer, packet, sent),
            functools.partial(_pack, sealed_packer, packet, sent),
        )
        out[f"server receive: datagram -> packet, {label}"] = (
            functools.partial(_next_decoded, functools.partial(_server_decode, plain),
                              itertools.repeat(plain_dgram)),
            functools.partial(_next_decoded, functools.partial(
                _server_decode, SealedCodec(key_b, key_a)), iter(sealed_dgrams)),
        )
        out[f"SDK receive: decode_datagram, {label}"] = (
            functools.partial(_next_decoded, plain.decode_datagram,
                              itertools.repeat(plain_dgram)),
            functools.partial(_next_decoded, SealedCodec(key_b, key_a).decode_datagram,
                              iter(sealed_dgrams)),
        )
    window, counters = ReplayWindow(), itertools.count(1)
    out["replay window check (sealed only)"] = (
        lambda: None, lambda: window.check(next(counters)))
    msg = plain.encode_datagram(one, 7)
    nonce, aad = bytes(12), msg[:12]
    chacha, gcm = ChaCha20Poly1305(key_a), AESGCM(key_a)
    out["AEAD only, 1 value: AES-256-GCM vs ChaCha20-Poly1305"] = (
        lambda: gcm.encrypt(nonce, msg, aad),
        lambda: chacha.encrypt(nonce, msg, aad),
    )
    if LIBSODIUM in IMPLEMENTATIONS:
        sodium = IMPLEMENTATIONS[LIBSODIUM](key_a)
        out["AEAD only, 1 value: ChaCha20-Poly1305, libsodium vs cryptography"] = (
            lambda: sodium.encrypt(nonce, msg, aad),
            lambda: chacha.encrypt(nonce, msg, aad),
        )
    return out


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
    for name, (plain, sealed) in cases(args.repeats * args.number).items():
        a: list[float] = []
        b: list[float] = []
        for _ in range(args.repeats):  # interleaved: both see the same machine load
            a.append(_cpu_ns(plain, args.number))
            b.append(_cpu_ns(sealed, args.number))
        ma, mb = statistics.median(a), statistics.median(b)
        print(f"| {name} | {ma:.0f} | {mb:.0f} | {mb - ma:+.0f} | {mb / ma:.2f} |")
    a_cold, b_cold = cold_hop(args.cold)
    print(f"| one hop at 1 kHz, caches cold (encode + decode, 1 value; median of {args.cold}; "
          f"sealing: {AEAD_STATE}) | {a_cold:.0f} | {b_cold:.0f} | {b_cold - a_cold:+.0f} | "
          f"{b_cold / a_cold:.2f} |")
    if LIBSODIUM in IMPLEMENTATIONS:
        a_cold, b_cold = cold_aead(args.cold)
        print(f"| AEAD only, 1 value, caches cold: ChaCha20-Poly1305, libsodium vs "
              f"cryptography (median of {args.cold}) | {a_cold:.0f} | {b_cold:.0f} | "
              f"{b_cold - a_cold:+.0f} | {b_cold / a_cold:.2f} |")
    load = os.getloadavg()
    print(f"\nload average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")


def _cpu_ns(call: Callable[[], object], number: int) -> float:
    """CPU nanoseconds per call of ``call`` (this thread's clock: preemption not counted)."""
    return timeit.Timer(call, timer=time.thread_time).timeit(number) / number * 1e9


def _cold(a: Callable[[int], object], b: Callable[[int], object],
          samples: int) -> tuple[float, float]:
    """Median CPU ns of ``a(i)`` and ``b(i)`` as a 1 kHz stream meets them: 1 ms apart, with
    8 MiB of other memory touched in between (the tight loops above run with every cache warm,
    which a control stream's datagrams never find). Interleaved."""
    other = [bytearray(1 << 20) for _ in range(8)]
    times: tuple[list[int], list[int]] = ([], [])
    for i in range(samples):
        for call, samples_of in zip((a, b), times, strict=True):
            for block in other:
                block[::4096] = b"\x01" * 256
            time.sleep(0.001)
            start = time.thread_time_ns()
            call(i)
            samples_of.append(time.thread_time_ns() - start)
    return statistics.median(times[0]), statistics.median(times[1])


def cold_hop(samples: int) -> tuple[float, float]:
    """One datagram's encode + decode, plain and sealed, cold (:func:`_cold`)."""
    key_a, key_b = os.urandom(32), os.urandom(32)
    plain, sender, receiver = PacketCodec(), SealedCodec(key_a, key_b), SealedCodec(key_b, key_a)
    return _cold(
        lambda i: plain.decode_datagram(plain.encode_datagram(Value(1, i, i, 1.5), 7)),
        lambda i: receiver.decode_datagram(sender.encode_datagram(Value(1, i, i, 1.5), 7)),
        samples)


def cold_aead(samples: int) -> tuple[float, float]:
    """One ChaCha20-Poly1305 seal of a 1-value datagram, libsodium's and cryptography's, cold."""
    key = os.urandom(32)
    sodium, openssl = IMPLEMENTATIONS[LIBSODIUM](key), ChaCha20Poly1305(key)
    msg, aad = bytes(34), bytes(20)
    return _cold(lambda i: sodium.encrypt(nonce(i + 1), msg, aad),
                 lambda i: openssl.encrypt(nonce(i + 1), msg, aad), samples)


if __name__ == "__main__":
    main()
