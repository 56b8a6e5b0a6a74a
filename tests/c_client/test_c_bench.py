"""The C side of benchmarks/c_client_rt.py (benchmarks/c_client/rlb_rt_bench.c), small and real.

Each mode against a real ``rlbridge serve`` (or the raw forwarder) on loopback: the loop runs
its periods, every value it writes is sent and arrives, and the JSON it prints holds what the
script reads. Timing figures belong to the benchmark; only counts are asserted here.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

from c_programs import CProcess

Server = Callable[..., tuple[int, subprocess.Popen[str]]]
DIST = {"n", "p50", "p90", "p99", "p999", "max"}


def _json(proc: CProcess | subprocess.CompletedProcess[str]) -> dict[str, Any]:
    out = proc.out if isinstance(proc, CProcess) else proc.stdout.splitlines()
    result: dict[str, Any] = json.loads(out[-1])
    return result


def _run(c_build: Path, *args: str) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([str(c_build / "rlb_rt_bench"), *args], capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return done


def test_jitter_loop_streams_every_value(c_build: Path, cli_server: Server) -> None:
    port, _ = cli_server()
    res = _json(_run(c_build, "jitter", "1", "127.0.0.1", str(port), "3"))
    assert res["written"] == res["sent"] == 3 * 1000  # 1 s of 1 kHz periods, 3 channels
    assert res["ring_full"] == 0
    assert res["late_us"]["n"] == 1000
    assert res["period_dev_us"]["n"] == 999
    assert set(res["write_ns"]) == DIST


def test_pub_to_sub_through_the_server(c_build: Path, cli_server: Server,
                                       c_processes: list[CProcess]) -> None:
    port, _ = cli_server()
    sub = CProcess(str(c_build / "rlb_rt_bench"), "sub", "127.0.0.1", str(port), "/bench_",
                   "2", "200", "60")
    c_processes.append(sub)
    sub.wait_err("ready")
    pub = _json(_run(c_build, "pub", "127.0.0.1", str(port), "/bench_", "2", "200", "1000"))
    assert sub.finish(timeout=90) == 0, sub.err
    got = _json(sub)
    assert pub["sent"] == got["received"] == got["latency_us"]["n"] == 400
    assert pub["cpu_us_per_value"] > 0
    assert got["cpu_us_per_value"] > 0


def test_raw_udp_baseline(c_build: Path, free_port: Callable[[], int],
                          c_processes: list[CProcess]) -> None:
    fwd_port, sub_port = free_port(), free_port()
    sub = CProcess(str(c_build / "rlb_rt_bench"), "rawsub", str(sub_port), "200", "60")
    fwd = CProcess(str(c_build / "rlb_rt_bench"), "rawfwd", str(fwd_port), str(sub_port),
                   "200", "60")
    c_processes.extend([sub, fwd])
    sub.wait_err("ready")
    fwd.wait_err("ready")
    pub = _json(_run(c_build, "rawpub", "127.0.0.1", str(fwd_port), "2", "100", "1000"))
    assert fwd.finish(timeout=90) == 0, fwd.err
    assert sub.finish(timeout=90) == 0, sub.err
    assert pub["sent"] == _json(fwd)["forwarded"] == _json(sub)["received"] == 200
    assert set(_json(sub)["latency_us"]) == DIST
