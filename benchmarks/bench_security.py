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

A second table gives what TLS costs the TCP transport: batched throughput and 1 kHz latency
(``TCP, nodelay``) of a server started with a certificate (``rlbridge tls init``'s) and clients
that pin its fingerprint, against the plain column's TCP runs. ``--no-tls`` leaves it out.

``--diagnose`` adds a latency row that splits the keyed cost: keyed sessions whose
ChaCha20-Poly1305 is replaced, in all three processes, by a stand-in that copies the bytes and
appends a zero tag (no security at all: a measurement only). That row is everything sealing
adds except the cipher call itself (handshake, counters, replay window, the sealed code
paths); the rest of the keyed row's gap is the cipher.

The keyed column seals with this install's ChaCha20-Poly1305 (libsodium's through
``rlbridge.wire._chacha`` when it was built: ``rlbridge --version`` says); ``--aead-compare``
adds keyed rows whose processes seal with cryptography's (``$RLBRIDGE_AEAD=cryptography``),
an A/B of the two libraries in the same run.

``--per-process`` splits the throughput rows' CPU per value by process (publisher, server,
subscriber), to see which one pays a keyed extra.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from rlbridge.bench import latency, throughput
from rlbridge.bench.common import BenchError, Link, LoopbackLink
from rlbridge.tls.certs import init_server
from rlbridge.wire.aead import AEAD_ENV, CRYPTOGRAPHY
from rlbridge.wire.aead import STATE as AEAD_STATE
from rlbridge.wire.auth import PSK_ENV


class KeyedLink:
    """``inner`` whose processes all get ``$RLBRIDGE_PSK`` (server and clients alike)."""

    def __init__(self, inner: Link, key_hex: str, env: dict[str, str] | None = None) -> None:
        self._inner = inner
        self._key = key_hex
        self._env = env or {}
        self.name = f"{inner.name} + PSK"

    def address(self, side: Any) -> str:
        return self._inner.address(side)

    def popen(self, side: Any, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        env = dict(kwargs.pop("env", None) or os.environ)
        env[PSK_ENV] = self._key
        env.update(self._env)
        return self._inner.popen(side, argv, env=env, **kwargs)


#: A client child's entry point with TLS: ``Bridge.connect`` pins the benchmark server's
#: certificate (the roles call it without TLS options), then the usual ``worker_main``.
_TLS_CHILD = (
    "import os; from rlbridge import Bridge, Tls; _connect = Bridge.connect\n"
    "def connect(*args, **kwargs):\n"
    "    kwargs.setdefault('security', Tls(fingerprint=os.environ['RLBRIDGE_BENCH_FINGERPRINT']))\n"
    "    return _connect(*args, **kwargs)\n"
    "Bridge.connect = connect\n"
    "from rlbridge.bench.child import worker_main; worker_main()")


class TlsLink:
    """``inner`` whose server has a TLS certificate and whose clients pin its fingerprint."""

    def __init__(self, inner: Link, cert: Path, key: Path, fingerprint: str) -> None:
        self._inner = inner
        self._files = {"tls_cert": str(cert), "tls_key": str(key)}
        self._fingerprint = fingerprint
        self.name = f"{inner.name} + TLS"

    def address(self, side: Any) -> str:
        return self._inner.address(side)

    def popen(self, side: Any, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        # argv: python -c <entry> <module> <role> <json params> <lifetime> (bench/workers.py)
        argv = list(argv)
        if argv[4] == "server":
            params = json.loads(argv[5])
            params["config"] = {**params.get("config", {}), **self._files}
            argv[5] = json.dumps(params)
        else:
            argv[2] = _TLS_CHILD
        env = dict(kwargs.pop("env", None) or os.environ)
        env["RLBRIDGE_BENCH_FINGERPRINT"] = self._fingerprint
        return self._inner.popen(side, argv, env=env, **kwargs)


#: ``--diagnose``: every child first replaces ChaCha20-Poly1305 by a copy + zero tag (before
#: rlbridge imports it), then runs the usual ``worker_main``. A measurement, never security.
_NOOP_CIPHER_CHILD = (
    "import cryptography.hazmat.primitives.ciphers.aead as aead\n"
    "from cryptography.exceptions import InvalidTag\n"
    "class NoopCipher:\n"
    "    def __init__(self, key): pass\n"
    "    def encrypt(self, nonce, data, aad): return bytes(data) + bytes(16)\n"
    "    def decrypt(self, nonce, data, aad):\n"
    "        if bytes(data[-16:]) != bytes(16): raise InvalidTag()\n"
    "        return bytes(data[:-16])\n"
    "aead.ChaCha20Poly1305 = NoopCipher\n"
    "from rlbridge.bench.child import worker_main; worker_main()")

#: ``--cipher-swap``: every child seals with AES-256-GCM where the code says ChaCha20-Poly1305
#: (the same interface and key, nonce and tag sizes; not interoperable with real peers: a
#: measurement of the alternative cipher on this path, not a mode).
_GCM_SWAP_CHILD = (
    "import cryptography.hazmat.primitives.ciphers.aead as aead\n"
    "aead.ChaCha20Poly1305 = aead.AESGCM\n"
    "from rlbridge.bench.child import worker_main; worker_main()")


class SwappedCipherLink(KeyedLink):
    """:class:`KeyedLink` whose processes start with ``entry`` (a cipher swapped in)."""

    def __init__(self, inner: Link, key_hex: str, entry: str, name: str) -> None:
        # cryptography's class is the one swapped: libsodium's must not be chosen over it.
        super().__init__(inner, key_hex, {AEAD_ENV: CRYPTOGRAPHY})
        self._entry = entry
        self.name = f"{inner.name} + PSK, {name}"

    def popen(self, side: Any, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        argv = list(argv)
        argv[2] = self._entry  # python -c <entry> ... (bench/workers.py)
        return super().popen(side, argv, **kwargs)


class TreeLink(KeyedLink):
    """:class:`KeyedLink` whose processes import rlbridge from another source tree (an A/B
    against the keyed code of a baseline checkout: ``--baseline TREE/src``)."""

    def __init__(self, inner: Link, key_hex: str, tree: str) -> None:
        super().__init__(inner, key_hex)
        self._tree = str(Path(tree).resolve())
        self.name = f"{inner.name} + PSK, {tree}"

    def popen(self, side: Any, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        env = dict(kwargs.pop("env", None) or os.environ)
        env["PYTHONPATH"] = self._tree
        return super().popen(side, argv, env=env, **kwargs)


def _plain_link() -> Link:
    link = LoopbackLink()
    os.environ.pop(PSK_ENV, None)  # the plain column must really be plain
    return link


T = TypeVar("T")

#: The processes of a throughput run whose CPU ``--per-process`` reports (bench/throughput.py).
_PROCESSES = ("publisher", "server", "subscriber")


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
    parser.add_argument("--no-tls", action="store_true", help="leave out the TLS table")
    parser.add_argument("--diagnose", action="store_true",
                        help="add keyed latency with a no-op cipher (module docstring)")
    parser.add_argument("--cipher-swap", action="store_true",
                        help="add keyed latency with AES-256-GCM swapped in for "
                        "ChaCha20-Poly1305 in every process (the alternative's cost)")
    parser.add_argument("--aead-compare", action="store_true",
                        help="add keyed rows sealing with cryptography's ChaCha20-Poly1305 in "
                        "every process ($RLBRIDGE_AEAD=cryptography), against the default "
                        "(libsodium's, when built): the same construction, another library")
    parser.add_argument("--baseline", metavar="TREE/src",
                        help="add keyed rows whose processes import rlbridge from this tree")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of the columns' order in each repeat (default: random)")
    parser.add_argument("--latency-only", action="store_true",
                        help="only the 1 kHz UDP latency rows (quick A/B of the sealing path)")
    parser.add_argument("--per-process", action="store_true",
                        help="add each process's CPU per value to the throughput rows "
                        "(publisher, server, subscriber: where a keyed extra is paid)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rlbridge-bench-tls-") as tmp:
        run(args, Path(tmp))


def run(args: argparse.Namespace, tmp: Path) -> None:
    tput_cases = {c.key: c for c in throughput.cases(args.batch)}
    lat_cases = {c.key: c for c in latency.CASES}
    udp_batch, tcp_batch = tput_cases["rlb-udp-batch"], tput_cases["rlb-tcp-batch"]
    udp_lat, tcp_lat = lat_cases["rlb-udp"], lat_cases["rlb-tcp-nodelay"]
    # What each column runs: (link, throughput rows, latency rows).
    plan: dict[str, tuple[Link, list[throughput.Case], list[latency.Case]]] = {
        "plain": (_plain_link(), [udp_batch, tcp_batch], [udp_lat]),
        "keyed": (KeyedLink(LoopbackLink(), os.urandom(32).hex()), [udp_batch, tcp_batch],
                  [udp_lat]),
    }
    if args.baseline:
        plan["baseline"] = (TreeLink(LoopbackLink(), os.urandom(32).hex(), args.baseline),
                            [udp_batch, tcp_batch], [udp_lat])
    if args.aead_compare:
        plan["cryptography"] = (KeyedLink(LoopbackLink(), os.urandom(32).hex(),
                                          {AEAD_ENV: CRYPTOGRAPHY}), [udp_batch, tcp_batch],
                                [udp_lat])
    if args.diagnose:
        plan["noop-cipher"] = (SwappedCipherLink(LoopbackLink(), os.urandom(32).hex(),
                                                 _NOOP_CIPHER_CHILD, "no-op cipher"),
                               [], [udp_lat])
    if args.cipher_swap:
        plan["gcm-swap"] = (SwappedCipherLink(LoopbackLink(), os.urandom(32).hex(),
                                              _GCM_SWAP_CHILD, "AES-256-GCM swapped in"),
                            [], [udp_lat])
    if args.latency_only:
        args.no_tls = True
        for _link, tput_rows, _lat in plan.values():
            tput_rows.clear()
    if not args.no_tls:
        cert, key, fingerprint = init_server(tmp / "tls")
        plan["plain"][2].append(tcp_lat)
        plan["tls"] = (TlsLink(LoopbackLink(), cert, key, fingerprint), [tcp_batch], [tcp_lat])
    tput: dict[tuple[str, str], list[float]] = {}
    cpu: dict[tuple[str, str], list[float]] = {}
    #: (case, column, process) -> CPU s per 1M values of that process (``--per-process``).
    cpu_of: dict[tuple[str, str, str], list[float]] = {}
    p50: dict[tuple[str, str], list[float]] = {}
    p99: dict[tuple[str, str], list[float]] = {}
    retries = dict.fromkeys(plan, 0)
    load_before = os.getloadavg()
    seed = random.randrange(1 << 32) if args.seed is None else args.seed
    order = random.Random(seed)
    for rep in range(args.repeats):
        # Interleaved (same load), in a new random order every repeat: a run may find the
        # previous run's processes still exiting, and no column may always follow the same one.
        names = list(plan)
        order.shuffle(names)
        for name in names:
            link, tput_rows, lat_rows = plan[name]
            for case in tput_rows:
                print(f"[{rep + 1}/{args.repeats}] {name} {case.label}", file=sys.stderr)
                m = _retrying(lambda lk=link, c=case: throughput.measure(  # type: ignore[misc]
                    lk, c, count=50_000_000, seconds=args.seconds), retries, name)
                tput.setdefault((case.key, name), []).append(m.rate)
                cpu.setdefault((case.key, name), []).append(m.cpu["total"])
                for process in _PROCESSES:
                    cpu_of.setdefault((case.key, name, process), []).append(m.cpu[process])
            for lcase in lat_rows:
                print(f"[{rep + 1}/{args.repeats}] {name} {lcase.label} 1 kHz latency",
                      file=sys.stderr)
                lm = _retrying(lambda lk=link, c=lcase: latency.measure(  # type: ignore[misc]
                    lk, c, rate_hz=1000.0, count=args.samples), retries, name)
                p50.setdefault((lcase.key, name), []).append(lm.p50)
                p99.setdefault((lcase.key, name), []).append(lm.p99)
    load_after = os.getloadavg()
    print(f"Command: `{' '.join(['.venv/bin/python', *sys.argv])}`  ")
    print(f"Keyed column's ChaCha20-Poly1305: {AEAD_STATE}  ")
    print(f"Load average before {load_before[0]:.2f}, after {load_after[0]:.2f}; "
          f"medians of {args.repeats} interleaved repeats; runs repeated after a failure "
          f"(a watchdog timeout under load): "
          + ", ".join(f"{k} {v}" for k, v in retries.items())
          + f"; columns in a random order per repeat (--seed {seed}).\n")

    def table(other: str, heading: str, tput_rows: list[throughput.Case],
              lat_rows: list[latency.Case]) -> None:
        med = statistics.median
        print(f"| path | plain | {heading} | {other} / plain |")
        print("|---|---:|---:|---:|")
        for case in tput_rows:
            a, b = med(tput[(case.key, "plain")]), med(tput[(case.key, other)])
            print(f"| {case.label}, values/s | {a:,.0f} | {b:,.0f} | {b / a:.2f} |")
            a, b = med(cpu[(case.key, "plain")]), med(cpu[(case.key, other)])
            print(f"| {case.label}, CPU s per 1M values (3 processes) | {a:.2f} | {b:.2f} | "
                  f"{b / a:.2f} |")
            for process in _PROCESSES if args.per_process else ():
                a = med(cpu_of[(case.key, "plain", process)])
                b = med(cpu_of[(case.key, other, process)])
                print(f"| {case.label}, CPU s per 1M values, {process} | {a:.3f} | {b:.3f} | "
                      f"{b / a:.2f} |")
        for lcase in lat_rows:
            for label, data in (("p50", p50), ("p99", p99)):
                a, b = med(data[(lcase.key, "plain")]), med(data[(lcase.key, other)])
                print(f"| {lcase.label} 1 kHz one-way latency {label}, us | {a:.0f} | {b:.0f} "
                      f"| {b / a:.2f} |")

    tput_keyed = [] if args.latency_only else [udp_batch, tcp_batch]
    table("keyed", "keyed (sealed)", tput_keyed, [udp_lat])
    if "cryptography" in plan:
        print()
        table("cryptography", "keyed, cryptography's AEAD", tput_keyed, [udp_lat])
    if "baseline" in plan:
        print()
        table("baseline", f"keyed, {args.baseline}", tput_keyed, [udp_lat])
        print()
    extra = {"noop-cipher": "diagnostic: keyed, cipher replaced by a no-op",
             "gcm-swap": "candidate: keyed, AES-256-GCM swapped in for ChaCha20-Poly1305"}
    if any(column in plan for column in extra):
        print("| path | plain | diagnostic or candidate | ratio |")
        print("|---|---:|---:|---:|")
    for column, what in extra.items():
        if column not in plan:
            continue
        for label, data in (("p50", p50), ("p99", p99)):
            a = statistics.median(data[(udp_lat.key, "plain")])
            b = statistics.median(data[(udp_lat.key, column)])
            print(f"| {what}, {udp_lat.label} 1 kHz latency {label}, us | {a:.0f} | {b:.0f} "
                  f"| {b / a:.2f} |")
    print()
    print("Paired: median over the repeats of each repeat's p50 / plain p50 (the same minute's "
          "load on both): " + ", ".join(
              f"{column} {_paired(p50, udp_lat.key, column):.3f}"
              for column in plan if column not in ("plain", "tls")) + ".")
    if "tls" in plan:
        print()
        table("tls", "TLS", [tcp_batch], [tcp_lat])


def _paired(data: dict[tuple[str, str], list[float]], key: str, column: str) -> float:
    """Median of the per-repeat ratios column / plain (runs of a repeat are minutes apart at
    most, so a ratio compares like load with like load)."""
    return statistics.median(b / a for a, b in zip(data[(key, "plain")], data[(key, column)],
                                                   strict=True))


if __name__ == "__main__":
    main()
