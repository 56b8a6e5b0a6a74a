"""CPU per value of each thread on the UDP value path at 1 kHz, sealed vs plain, in one process.

Run: ``.venv/bin/python benchmarks/bench_seal_path.py [--repeats 7] [--values 2000]``. Prints a
Markdown table (docs/benchmarks.md quotes it).

One process holds a real server (``ServerThread``, the in-process adapter), a publisher
``Bridge`` and a subscriber ``Bridge``, connected over loopback UDP: plain, or with a
pre-shared key (server ``psk_file``, SDK ``psk=``), with which every datagram is sealed
(docs/protocol.md section 16). The publisher writes one value per millisecond (``--rate``), so
each value is a datagram of its own both ways, as in the 1 kHz latency benchmark. For each of
the three threads a value crosses, the table gives its CPU time per value: the publisher's send
thread (wake-up, encode, seal, ``send``), the server's event-loop thread (wake-up, receive,
open, decode, publish, encode, seal, ``sendto``) and the subscriber's receive thread (wake-up,
receive, open, decode, hand to the channel). CPU time is the kernel's per-thread run time
(``/proc/self/task/<tid>/schedstat``, nanoseconds), not wall time, so waiting for a core or for
the GIL is not counted; but at 1 kHz every wake-up meets caches that other processes have
filled, so on a loaded machine a repeat can move by a third either way: read the medians of
many repeats, and ``bench_seal.py`` for the per-datagram functions alone. Plain and keyed runs
alternate in every repeat. ``--cipher-swap`` adds keyed runs that seal with AES-256-GCM
instead of ChaCha20-Poly1305 (same key, nonce and tag sizes), ``--diagnose`` keyed runs whose
cipher only copies the bytes and appends a zero tag (everything sealing adds but the cipher:
a measurement, never security), ``--part-by-part`` keyed runs whose send thread packs a sealed
round part by part, as it did before sealed rounds took the one-call way (an A/B of that
change in the same run).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import AESGCM, ChaCha20Poly1305

from rlbridge import Psk
from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerConfig
from rlbridge.server.app import ServerThread
from rlbridge.wire import seal
from rlbridge.wire.auth import PSK_ENV
from rlbridge.wire.bundle import DatagramPacker

TOPIC = "/bench/seal_path"
MSG_TYPE = "std_msgs/msg/Int64"
THREADS = ("SDK send thread (publisher)", "server event loop", "SDK receive thread (subscriber)")


def thread_cpu_ns(native_id: int) -> int:
    """Nanoseconds thread ``native_id`` of this process has run (all CPUs)."""
    with open(f"/proc/self/task/{native_id}/schedstat", "rb") as f:
        return int(f.read().split()[0])


def run_once(key_hex: str | None, key_file: Path | None, values: int,
             rate_hz: float) -> tuple[list[float], int]:
    """One run: (CPU ns per value of each of THREADS, values the subscriber read)."""
    config = ServerConfig(port=0, psk_file=key_file, heartbeat_ms=200, timeout_ms=5000)
    key = None if key_hex is None else Psk(key=key_hex)
    with ServerThread(config) as server:
        pub = Bridge.connect("127.0.0.1", server.port, name="seal-path-pub",
                             security=key)
        sub = Bridge.connect("127.0.0.1", server.port, name="seal-path-sub",
                             security=key)
        try:
            inp = sub.subscribe(TOPIC, MSG_TYPE, "data", transport="udp", blocking=True,
                                buffer_size=4096)
            out = pub.publish(TOPIC, MSG_TYPE, "data", transport="udp")
            got = [0]
            stop = threading.Event()

            def drain() -> None:
                while not stop.is_set():
                    try:
                        inp.read(0.05)
                    except TimeoutError:
                        continue
                    got[0] += 1

            reader = threading.Thread(target=drain, name="seal-path-reader", daemon=True)
            reader.start()
            for i in range(50):  # warm-up: the first values set up paths and caches
                out.write(i)
                time.sleep(0.001)
            time.sleep(0.3)
            assert server._thread is not None  # started by the with block
            tids = [pub._sender.native_id, server._thread.native_id,
                    sub._conn.receive_thread_id]
            assert all(t is not None for t in tids), tids
            before = [thread_cpu_ns(t) for t in tids]  # type: ignore[arg-type]
            got0 = got[0]
            period = 1.0 / rate_hz
            start = time.monotonic()
            for i in range(values):
                delay = start + i * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                out.write(i)
            time.sleep(0.3)  # the last values' way through
            after = [thread_cpu_ns(t) for t in tids]  # type: ignore[arg-type]
            read = got[0] - got0
            stop.set()
            reader.join(2.0)
        finally:
            pub.close()
            sub.close()
    return [(b - a) / values for a, b in zip(before, after, strict=True)], read


class _NoopCipher:
    """``--diagnose``: copies the bytes and appends a zero tag (no security: a measurement)."""

    def __init__(self, key: bytes) -> None:
        del key

    def encrypt(self, nonce: bytes, data: bytes, aad: bytes) -> bytes:
        return bytes(data) + bytes(16)

    def decrypt(self, nonce: bytes, data: bytes, aad: bytes) -> bytes:
        if bytes(data[-16:]) != bytes(16):
            raise InvalidTag
        return bytes(data[:-16])


@contextlib.contextmanager
def _variant(name: str) -> Iterator[None]:
    """What a column changes in this process for its run (then puts back)."""
    with contextlib.ExitStack() as stack:
        cipher = {"keyed, AES-256-GCM swapped in": AESGCM,
                  "keyed, no-op cipher": _NoopCipher}.get(name)
        if cipher is not None:  # sessions opened from now on seal with it, on both ends
            stack.callback(setattr, seal, "ChaCha20Poly1305", ChaCha20Poly1305)
            setattr(seal, "ChaCha20Poly1305", cipher)  # noqa: B010 (another type on purpose)
        if name == "keyed, rounds part by part":  # the send thread's sealed path before 11-28
            stack.callback(setattr, DatagramPacker, "one_call", DatagramPacker.one_call)
            setattr(DatagramPacker, "one_call",  # noqa: B010
                    property(lambda packer: packer._plain and packer.bundles))
        yield


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--values", type=int, default=2000, help="values per run")
    parser.add_argument("--rate", type=float, default=1000.0, help="values per second")
    parser.add_argument("--cipher-swap", action="store_true",
                        help="add keyed runs sealing with AES-256-GCM instead of "
                        "ChaCha20-Poly1305 (the alternative's cost)")
    parser.add_argument("--part-by-part", action="store_true",
                        help="add keyed runs whose send thread packs a sealed round part by "
                        "part (the path before sealed rounds took the one-call way)")
    parser.add_argument("--diagnose", action="store_true",
                        help="add keyed runs whose AEADs copy the bytes and append a zero tag")
    args = parser.parse_args()
    os.environ.pop(PSK_ENV, None)  # the plain runs must really be plain
    key_hex = os.urandom(32).hex()
    names = ["plain", "keyed"]
    if args.cipher_swap:
        names.append("keyed, AES-256-GCM swapped in")
    if args.part_by_part:
        names.append("keyed, rounds part by part")
    if args.diagnose:
        names.append("keyed, no-op cipher")
    cpu: dict[str, list[list[float]]] = {name: [] for name in names}
    delivered: dict[str, list[int]] = {name: [] for name in names}
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        key_file = Path(tmp, "keys")
        key_file.write_text(key_hex + "\n")
        key_file.chmod(0o600)
        for rep in range(args.repeats):
            for name in names:
                keyed = name != "plain"
                with _variant(name):
                    per_value, read = run_once(key_hex if keyed else None,
                                               key_file if keyed else None, args.values,
                                               args.rate)
                cpu[name].append(per_value)
                delivered[name].append(read)
                print(f"[{rep + 1}/{args.repeats}] {name}: "
                      + ", ".join(f"{x / 1000:.1f}" for x in per_value)
                      + f" us/value; {read}/{args.values} read", flush=True)
    load_after = os.getloadavg()[0]
    print(f"\nCommand: `{' '.join(['.venv/bin/python', *sys.argv])}`  ")
    print(f"Load average before {load_before:.2f}, after {load_after:.2f}; medians of "
          f"{args.repeats} interleaved repeats of {args.values} values at {args.rate:g} Hz; "
          "values read per run: " + ", ".join(
              f"{n} {min(delivered[n])}-{max(delivered[n])}" for n in names) + ".\n")
    for other in names[1:]:
        _table(cpu, other)
        print()


def _table(cpu: dict[str, list[list[float]]], other: str) -> None:
    print(f"| thread (CPU per value) | plain us | {other} us | extra us | ratio |")
    print("|---|---:|---:|---:|---:|")
    med = statistics.median
    for i, label in enumerate(THREADS):
        a = med(run[i] for run in cpu["plain"]) / 1000
        b = med(run[i] for run in cpu[other]) / 1000
        print(f"| {label} | {a:.1f} | {b:.1f} | {b - a:+.1f} | {b / a:.2f} |")
    a, b = med(sum(run) for run in cpu["plain"]) / 1000, med(sum(run) for run in cpu[other]) / 1000
    print(f"| all three | {a:.1f} | {b:.1f} | {b - a:+.1f} | {b / a:.2f} |")


if __name__ == "__main__":
    main()
