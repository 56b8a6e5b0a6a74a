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
alternate in every repeat.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

from rlbridge.csp.bridge import Bridge
from rlbridge.server import ServerConfig
from rlbridge.server.app import ServerThread
from rlbridge.wire.auth import PSK_ENV

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
    with ServerThread(config) as server:
        pub = Bridge.connect("127.0.0.1", server.port, name="seal-path-pub", psk=key_hex)
        sub = Bridge.connect("127.0.0.1", server.port, name="seal-path-sub", psk=key_hex)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--values", type=int, default=2000, help="values per run")
    parser.add_argument("--rate", type=float, default=1000.0, help="values per second")
    args = parser.parse_args()
    os.environ.pop(PSK_ENV, None)  # the plain runs must really be plain
    key_hex = os.urandom(32).hex()
    cpu: dict[str, list[list[float]]] = {"plain": [], "keyed": []}
    delivered: dict[str, list[int]] = {"plain": [], "keyed": []}
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        key_file = Path(tmp, "keys")
        key_file.write_text(key_hex + "\n")
        key_file.chmod(0o600)
        for rep in range(args.repeats):
            for name in ("plain", "keyed"):
                keyed = name == "keyed"
                per_value, read = run_once(key_hex if keyed else None,
                                           key_file if keyed else None, args.values, args.rate)
                cpu[name].append(per_value)
                delivered[name].append(read)
                print(f"[{rep + 1}/{args.repeats}] {name}: "
                      + ", ".join(f"{x / 1000:.1f}" for x in per_value)
                      + f" us/value; {read}/{args.values} read", flush=True)
    load_after = os.getloadavg()[0]
    print(f"\nLoad average before {load_before:.2f}, after {load_after:.2f}; medians of "
          f"{args.repeats} interleaved repeats of {args.values} values at {args.rate:g} Hz; "
          f"values read: plain {min(delivered['plain'])}-{max(delivered['plain'])}, keyed "
          f"{min(delivered['keyed'])}-{max(delivered['keyed'])} per run.\n")
    print("| thread (CPU per value) | plain us | keyed (sealed) us | extra us | keyed / plain |")
    print("|---|---:|---:|---:|---:|")
    totals = {name: [sum(run) for run in runs] for name, runs in cpu.items()}
    for i, label in enumerate(THREADS):
        a = statistics.median(run[i] for run in cpu["plain"]) / 1000
        b = statistics.median(run[i] for run in cpu["keyed"]) / 1000
        print(f"| {label} | {a:.1f} | {b:.1f} | {b - a:+.1f} | {b / a:.2f} |")
    a, b = statistics.median(totals["plain"]) / 1000, statistics.median(totals["keyed"]) / 1000
    print(f"| all three | {a:.1f} | {b:.1f} | {b - a:+.1f} | {b / a:.2f} |")


if __name__ == "__main__":
    main()
