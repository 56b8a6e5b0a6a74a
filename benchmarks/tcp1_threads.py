"""Which thread limits TCP one value per frame: CPU of every thread of the three processes.

    .venv/bin/python benchmarks/tcp1_threads.py [--seconds 6] [--tree src] [--spy server]

The shape of ``rlbridge bench throughput``'s ``rlb-tcp-1`` row: a server with ``max_batch=1``
(every frame one value, both hops), an SDK publisher calling ``write`` per value (waiting while
more than half of its 64 Ki ring is unsent, as the bench's does), an SDK subscriber reading a
blocking channel. After a second of warm-up it reads every thread's CPU time from
``/proc/<pid>/task/<tid>/stat`` over the steady window and prints each thread's share of one
CPU (named by the Python thread that runs it) and the CPU µs per value; a thread near 100 %
is the bottleneck, and on a loaded machine, where none gets a whole core, the one with the
most CPU per value is. ``--spy <role>`` also records that process with ``py-spy record -f raw``
(into ``/tmp/tcp1_<role>.txt``) over the window. ``--tree`` puts a source tree first on the
children's ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

F64 = "std_msgs/msg/Float64"
TOPIC = "/tcp1/threads"


def _names() -> dict[str, str]:
    """This process's threads: native id -> Python thread name."""
    return {str(t.native_id): t.name for t in threading.enumerate() if t.native_id is not None}


def _emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def server(port: int, _seconds: float) -> None:
    from rlbridge.server import ServerConfig, ServerThread

    srv = ServerThread(ServerConfig(port=port, max_batch=1, timeout_ms=5000)).start()
    _emit(ready=True, threads=_names())
    sys.stdin.readline()
    srv.stop()


def publisher(port: int, seconds: float) -> None:
    from rlbridge.client.bridge import Bridge

    bridge = Bridge.connect("127.0.0.1", port, name="tcp1-pub")
    out = bridge.publish(TOPIC, F64, "data", transport="tcp", buffer_size=1 << 16)
    _emit(ready=True, threads=_names())
    sys.stdin.readline()
    end = time.monotonic() + seconds
    sent = 0
    write, pending = out.write, out.pending
    while time.monotonic() < end:
        while pending() > 1 << 15:
            time.sleep(0.0001)
        for v in range(256):
            write(float(v))
        sent += 256
    _emit(sent=sent)
    sys.stdin.readline()
    bridge.close()


def subscriber(port: int, seconds: float) -> None:
    from rlbridge.client.bridge import Bridge

    bridge = Bridge.connect("127.0.0.1", port, name="tcp1-sub")
    ch = bridge.subscribe(TOPIC, F64, "data", transport="tcp", blocking=True,
                          buffer_size=1 << 18)
    _emit(ready=True, threads=_names())
    got = 0
    first = last = 0.0
    end = time.monotonic() + seconds + 3.0
    while time.monotonic() < end:
        try:
            ch.read(0.05)
        except TimeoutError:
            continue
        got += 1 + len(ch.read_many())
        last = time.monotonic()
        first = first or last
    _emit(got=got, rate=got / max(last - first, 1e-9), lost=ch.lost)
    bridge.close()


def _cpu_ticks(pid: int) -> dict[str, int]:
    """utime + stime (clock ticks) of every thread of ``pid``, by thread id."""
    out: dict[str, int] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[tid] = int(fields[11]) + int(fields[12])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=6.0)
    p.add_argument("--tree", default="", help="src/ of the tree to run (default: installed)")
    p.add_argument("--spy", choices=("publisher", "server", "subscriber"), default=None)
    if len(sys.argv) > 1 and sys.argv[1] in ROLES:
        ROLES[sys.argv[1]](int(sys.argv[2]), float(sys.argv[3]))
        return
    args = p.parse_args()
    env = dict(os.environ)
    if args.tree:
        env["PYTHONPATH"] = str(Path(args.tree).resolve())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    procs: dict[str, subprocess.Popen[str]] = {}
    names: dict[str, dict[str, str]] = {}
    try:
        for role in ("server", "subscriber", "publisher"):
            proc = subprocess.Popen([sys.executable, __file__, role, str(port), str(args.seconds)],
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                    env=env)
            procs[role] = proc
            assert proc.stdout is not None
            assert proc.stdin is not None
            names[role] = json.loads(proc.stdout.readline())["threads"]
        pub = procs["publisher"]
        assert pub.stdin is not None
        assert pub.stdout is not None
        pub.stdin.write("go\n")
        pub.stdin.flush()
        time.sleep(1.0)
        window = max(1.0, args.seconds - 1.5)
        spy = None
        if args.spy:
            spy = subprocess.Popen(
                [str(Path(sys.executable).with_name("py-spy")), "record", "-r", "400", "-f",
                 "raw", "-o", f"/tmp/tcp1_{args.spy}.txt", "-p", str(procs[args.spy].pid),
                 "-d", str(int(window))], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        before = {role: _cpu_ticks(proc.pid) for role, proc in procs.items()}
        t0 = time.monotonic()
        time.sleep(window)
        after = {role: _cpu_ticks(proc.pid) for role, proc in procs.items()}
        elapsed = time.monotonic() - t0
        if spy is not None:
            spy.wait(60)
        sent = json.loads(pub.stdout.readline())["sent"]
        sub = procs["subscriber"]
        assert sub.stdout is not None
        result = json.loads(sub.stdout.readline())
    finally:
        for proc in procs.values():
            if proc.stdin is not None and not proc.stdin.closed:
                proc.stdin.write("end\n")
                proc.stdin.close()
        for proc in procs.values():
            proc.wait(30)
    hz = os.sysconf("SC_CLK_TCK")
    rate = result["rate"]
    print(f"{rate:,.0f} values/s, {result['got']:,} of {sent:,} read, {result['lost']} lost; "
          f"window {elapsed:.1f} s; load average {os.getloadavg()[0]:.2f}")
    print(f"{'process':12}{'thread':24}{'% of a CPU':>11}{'CPU us/value':>14}")
    for role in procs:
        for tid, ticks in sorted(after[role].items()):
            cpu = (ticks - before[role].get(tid, 0)) / hz / elapsed
            if cpu > 0.005:
                name = names[role].get(tid, "(other)")
                print(f"{role:12}{name:24}{100 * cpu:10.1f}%{1e6 * cpu / rate:14.2f}")


ROLES = {"server": server, "publisher": publisher, "subscriber": subscriber}

if __name__ == "__main__":
    main()
