"""The C client's real-time figures (issue 28, point 6), every baseline in the same run.

    .venv/bin/python benchmarks/c_client_rt.py [--seconds 10] [--count 3000] [--rounds 1]
        [--out benchmarks/results/c_client_rt.json]

Builds clients/c (``build/c-bench``, its ``rlb_rt_bench``: benchmarks/c_client/rlb_rt_bench.c),
then, against real ``rlbridge serve`` processes on loopback:

(a) Jitter: a 1 kHz SCHED_FIFO loop (priority 80, mlockall, clock_nanosleep TIMER_ABSTIME)
    alone and writing 10 channels that the client streams to the server, each for --seconds,
    on an idle machine and under ``stress -c 2`` (as the thesis measured), the two loops
    alternating within one stress run. Wake-up lateness and |period - 1 ms|, and the loop's
    cost per rlb_write_f64.
(b) CPU per value and one-way latency of 10 channels at 1 kHz (--count values each), three
    paths in turn: the C client (rlb_rt_bench pub -> rlbridge serve -> rlb_rt_bench sub; its
    I/O thread takes the rings' values every 1000 us, the default, and every 100 us), raw
    UDP (one sendto(2) per value from the loop -> a C forwarder standing in for the server ->
    a C receiver), and the Python SDK (Bridge publisher -> rlbridge serve -> Bridge
    subscriber, one reader thread per channel). Each value is its CLOCK_REALTIME send time;
    latency = receive time - value. CPU per value: the sender's whole process (its I/O thread
    included), the middle (server or forwarder) and the receiver.

Prints the tables (medians over --rounds) and writes every run's raw figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = 10
RATE_HZ = 1000

SDK = r"""
import json, os, sys, threading, time
from rlbridge import Bridge
role, prefix = sys.argv[1], sys.argv[3]
port, n, count = int(sys.argv[2]), int(sys.argv[4]), int(sys.argv[5])
topics = [f"{prefix}{i}" for i in range(n)]
with Bridge.connect("127.0.0.1", port, timeout=10.0) as b:
    if role == "pub":
        out = [b.publish(t, "std_msgs/msg/Float64", transport="udp") for t in topics]
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))  # as the C loop
        except OSError:
            pass
        cpu0, start = time.process_time(), time.monotonic_ns()
        for i in range(count):
            delay = start + (i + 1) * 1_000_000 - time.monotonic_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
            for ch in out:
                ch.write(time.time())
        b.send(wait=True)
        cpu = time.process_time() - cpu0
        print(json.dumps({"mode": "sdkpub", "sent": n * count,
                          "cpu_us_per_value": cpu / (n * count) * 1e6}), flush=True)
    else:
        chans = [b.subscribe(t, "std_msgs/msg/Float64", transport="udp", blocking=True,
                             buffer_size=count) for t in topics]
        print("ready", file=sys.stderr, flush=True)
        lat = [[] for _ in topics]
        first = []
        def read(i):
            for _ in range(count):
                try:
                    v = chans[i].read(timeout=10.0)
                except TimeoutError:
                    return
                if not first:
                    first.append(time.process_time())
                lat[i].append((time.time() - v) * 1e6)
        threads = [threading.Thread(target=read, args=(i,)) for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        got = sorted(x for l in lat for x in l)
        cpu = time.process_time() - (first[0] if first else 0.0)
        q = lambda p: got[int((len(got) - 1) * p)] if got else 0.0
        print(json.dumps({"mode": "sdksub", "received": len(got),
                          "cpu_us_per_value": cpu / max(len(got), 1) * 1e6,
                          "latency_us": {"n": len(got), "p50": q(0.5), "p90": q(0.9),
                                         "p99": q(0.99), "p999": q(0.999),
                                         "max": got[-1] if got else 0.0}}), flush=True)
"""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u, \
            socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t:
        t.bind(("127.0.0.1", 0))
        port: int = t.getsockname()[1]
        u.bind(("127.0.0.1", port))  # the server takes both
        return port


def build() -> Path:
    out = ROOT / "build" / "c-bench"
    subprocess.run(["cmake", "-S", str(ROOT / "clients" / "c"), "-B", str(out),
                    "-DCMAKE_BUILD_TYPE=Release", "-DRLB_TESTS=OFF"], check=True,
                   capture_output=True)
    subprocess.run(["cmake", "--build", str(out), "-j", "2", "--target", "rlb_rt_bench"],
                   check=True, capture_output=True)
    return out / "rlb_rt_bench"


def proc_cpu(pid: int) -> float:
    """CPU seconds of a running process's live threads, in ns (schedstat; /proc/PID/stat
    counts clock ticks, too coarse for a few seconds of a server)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError):
            continue  # the thread ended meanwhile
    return total / 1e9


@contextmanager
def server() -> Iterator[tuple[int, int]]:
    """``rlbridge serve`` on a free port: (port, pid), ready for a session."""
    port = free_port()
    exe = Path(sys.executable).with_name("rlbridge")
    proc = subprocess.Popen([str(exe), "serve", "--port", str(port), "--log-level", "warning"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"rlbridge serve did not start: {proc.stderr}") from None
                time.sleep(0.1)
        time.sleep(0.3)
        yield port, proc.pid
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


@contextmanager
def stress(seconds: float) -> Iterator[None]:
    """``stress -c 2`` for at most ``seconds`` (its own process group, ended by its id)."""
    if shutil.which("stress") is None:
        raise SystemExit("stress is not installed (apt-get install stress)")
    proc = subprocess.Popen(["stress", "-c", "2", "-t", f"{int(seconds) + 1}s"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    time.sleep(1.0)
    try:
        yield
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=20)


def steal_ms() -> float:
    """The machine's stolen time so far (/proc/stat): a VM's vCPUs not running at all, which
    no priority inside the guest can prevent (it shows in every loop's maximum alike)."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()
    return int(fields[8]) * 1000 / os.sysconf("SC_CLK_TCK")


def run_json(argv: list[str], timeout: float) -> dict[str, Any]:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, check=False)
    if done.returncode != 0 or not done.stdout.strip():
        raise RuntimeError(f"{argv[:2]} exited {done.returncode}: {done.stderr[-500:]}")
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


class Reader:
    """A receiving process started first; its JSON once the sender is done."""

    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        assert self.proc.stderr is not None
        line = self.proc.stderr.readline()  # "ready": bound, values from now on reach it
        if "ready" not in line:
            self.proc.kill()
            raise RuntimeError(f"{argv[:2]} did not get ready: {line}")

    def result(self, timeout: float) -> dict[str, Any]:
        out, err = self.proc.communicate(timeout=timeout)
        if not out.strip():
            raise RuntimeError(f"reader exited {self.proc.returncode}: {err[-500:]}")
        result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
        return result


def jitter(bench: Path, seconds: int, rounds: int) -> list[dict[str, Any]]:
    runs: list[dict[str, Any]] = []
    for load in ("idle", "stress -c 2"):
        loaded = stress(rounds * 2 * (seconds + 3) + 10) if load != "idle" else _nothing()
        with server() as (port, _pid), loaded:
            for r in range(rounds):
                for streaming in ((False, True) if r % 2 == 0 else (True, False)):
                    argv = [str(bench), "jitter", str(seconds)]
                    if streaming:
                        argv += ["127.0.0.1", str(port), str(CHANNELS)]
                    steal0, loadavg = steal_ms(), os.getloadavg()[0]
                    res = run_json(argv, seconds * 3 + 30)
                    res.update(load=load, streaming=streaming, round=r, loadavg_1min=loadavg,
                               steal_ms=steal_ms() - steal0)
                    runs.append(res)
                    print(f"  jitter {load:11} {'streaming' if streaming else 'alone':9} "
                          f"late p50 {res['late_us']['p50']:.1f} p99 "
                          f"{res['late_us']['p99']:.1f} max {res['late_us']['max']:.0f} us "
                          f"(load {loadavg:.1f}, steal {res['steal_ms']:.0f} ms)", flush=True)
    return runs


@contextmanager
def _nothing() -> Iterator[None]:
    yield


def path_c(bench: Path, count: int, period_us: int) -> dict[str, Any]:
    with server() as (port, pid):
        sub = Reader([str(bench), "sub", "127.0.0.1", str(port), "/cl_", str(CHANNELS),
                      str(count), str(count / RATE_HZ + 30)])
        cpu0 = proc_cpu(pid)
        pub = run_json([str(bench), "pub", "127.0.0.1", str(port), "/cl_", str(CHANNELS),
                        str(count), str(RATE_HZ), str(period_us)], count / RATE_HZ + 60)
        recv = sub.result(count / RATE_HZ + 60)
        middle = (proc_cpu(pid) - cpu0) / max(recv["received"], 1) * 1e6
    return {"path": f"C client, I/O period {period_us} us", "pub": pub,
            "middle_cpu_us_per_value": middle, "sub": recv}


def path_raw(bench: Path, count: int) -> dict[str, Any]:
    total = str(CHANNELS * count)
    fwd_port, sub_port = free_port(), free_port()
    sub = Reader([str(bench), "rawsub", str(sub_port), total, str(count / RATE_HZ + 30)])
    fwd = Reader([str(bench), "rawfwd", str(fwd_port), str(sub_port), total,
                  str(count / RATE_HZ + 30)])
    pub = run_json([str(bench), "rawpub", "127.0.0.1", str(fwd_port), str(CHANNELS),
                    str(count), str(RATE_HZ)], count / RATE_HZ + 60)
    recv = sub.result(count / RATE_HZ + 60)
    middle = fwd.result(count / RATE_HZ + 60)
    return {"path": "raw UDP", "pub": pub,
            "middle_cpu_us_per_value": middle["cpu_us_per_value"], "sub": recv}


def path_sdk(count: int) -> dict[str, Any]:
    with server() as (port, pid):
        sub = Reader([sys.executable, "-c", SDK, "sub", str(port), "/py_", str(CHANNELS),
                      str(count)])
        cpu0 = proc_cpu(pid)
        pub = run_json([sys.executable, "-c", SDK, "pub", str(port), "/py_", str(CHANNELS),
                        str(count)], count / RATE_HZ + 60)
        recv = sub.result(count / RATE_HZ + 60)
        middle = (proc_cpu(pid) - cpu0) / max(recv["received"], 1) * 1e6
    return {"path": "Python SDK", "pub": pub, "middle_cpu_us_per_value": middle, "sub": recv}


def median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def tables(jit: list[dict[str, Any]], paths: list[dict[str, Any]], count: int) -> str:
    lines = ["| load | loop | late p50 | late p99 | late max | abs(period-1ms) p99 | "
             "write per value |", "|---|---|---|---|---|---|---|"]
    for load in ("idle", "stress -c 2"):
        for streaming in (False, True):
            rs = [r for r in jit if r["load"] == load and r["streaming"] == streaming]
            write = (f"{median([r['write_ns']['p50'] for r in rs]) / 1e3:.2f} us"
                     if streaming else "-")
            lines.append(
                f"| {load} | {'10 channels streaming' if streaming else 'alone'} | "
                f"{median([r['late_us']['p50'] for r in rs]):.1f} us | "
                f"{median([r['late_us']['p99'] for r in rs]):.1f} us | "
                f"{median([r['late_us']['max'] for r in rs]):.0f} us | "
                f"{median([r['period_dev_us']['p99'] for r in rs]):.1f} us | {write} |")
    lines += ["", "| path | latency p50 | p90 | p99 | sender CPU/value | middle CPU/value | "
              "receiver CPU/value | received |", "|---|---|---|---|---|---|---|---|"]
    for name in ("raw UDP", "C client, I/O period 1000 us", "C client, I/O period 100 us",
                 "Python SDK"):
        rs = [p for p in paths if p["path"] == name]

        def m(get: Any, rs: list[dict[str, Any]] = rs) -> float:
            return median([float(get(p)) for p in rs])
        lines.append(
            f"| {name} | {m(lambda p: p['sub']['latency_us']['p50']):.0f} us | "
            f"{m(lambda p: p['sub']['latency_us']['p90']):.0f} us | "
            f"{m(lambda p: p['sub']['latency_us']['p99']):.0f} us | "
            f"{m(lambda p: p['pub']['cpu_us_per_value']):.2f} us | "
            f"{m(lambda p: p['middle_cpu_us_per_value']):.2f} us | "
            f"{m(lambda p: p['sub']['cpu_us_per_value']):.2f} us | "
            f"{int(m(lambda p: p['sub']['received']))} of {CHANNELS * count} |")
    def p50(name: str, get: Callable[[dict[str, Any]], float]) -> float:
        return median([get(p) for p in paths if p["path"] == name])

    c, raw, sdk = "C client, I/O period 1000 us", "raw UDP", "Python SDK"

    def lat(p: dict[str, Any]) -> float:
        return float(p["sub"]["latency_us"]["p50"])

    def cpu(p: dict[str, Any]) -> float:
        return float(p["pub"]["cpu_us_per_value"])

    if all(any(p["path"] == n for p in paths) for n in (c, raw, sdk)):
        lines += ["", "C client (1000 us) / raw UDP: latency p50 "
                  f"x{p50(c, lat) / p50(raw, lat):.2f}, sender CPU "
                  f"x{p50(c, cpu) / p50(raw, cpu):.2f}; C client / Python SDK: "
                  f"latency p50 x{p50(c, lat) / p50(sdk, lat):.2f}, sender CPU "
                  f"x{p50(c, cpu) / p50(sdk, cpu):.2f}"]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=int, default=10, help="per jitter run (default 10)")
    parser.add_argument("--count", type=int, default=3000,
                        help="values per channel per latency run (default 3000: 3 s)")
    parser.add_argument("--rounds", type=int, default=1, help="repetitions (default 1)")
    parser.add_argument("--out", type=Path, default=None, help="write the raw runs as JSON")
    args = parser.parse_args()
    if not 1 <= args.seconds <= 120 or not 100 <= args.count <= 60000 \
            or not 1 <= args.rounds <= 10:
        parser.error("--seconds 1..120, --count 100..60000, --rounds 1..10")
    bench = build()
    print("jitter (1 kHz SCHED_FIFO loop):", flush=True)
    jit = jitter(bench, args.seconds, args.rounds)
    paths: list[dict[str, Any]] = []
    print("latency and CPU (10 channels x 1 kHz):", flush=True)
    for r in range(args.rounds):
        order: list[Callable[[], dict[str, Any]]] = [lambda: path_raw(bench, args.count),
                 lambda: path_c(bench, args.count, 1000),
                 lambda: path_c(bench, args.count, 100),
                 lambda: path_sdk(args.count)]
        for run in order if r % 2 == 0 else order[::-1]:
            res = run()
            res["round"] = r
            paths.append(res)
            print(f"  {res['path']:30} latency p50 {res['sub']['latency_us']['p50']:.0f} us, "
                  f"sender {res['pub']['cpu_us_per_value']:.2f} us/value, received "
                  f"{res['sub']['received']}", flush=True)
    print()
    print(tables(jit, paths, args.count))
    if args.out:
        args.out.write_text(json.dumps({"jitter": jit, "paths": paths,
                                        "argv": sys.argv[1:]}, indent=1))


if __name__ == "__main__":
    main()
