"""The pattern examples (examples/patterns/) run end to end against a live server.

Each example is a real process, as a user would start it; the receive examples start their own
publisher process. They run from a copy outside the checkout, as after ``pip install
rlbridge-sdk``: nothing but the installed package and the example files. Checked: the example
exits cleanly and reports its loop and channels, and the values went where the pattern says
(counters in the report), not how punctual the loop was.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from rlbridge.server import ServerConfig, ServerThread

CHECKOUT = Path(__file__).resolve().parents[2]
EXAMPLES = CHECKOUT / "examples" / "patterns"


@pytest.fixture(scope="module")
def port() -> Iterator[int]:
    with ServerThread(ServerConfig(port=0)) as srv:
        yield srv.port


@pytest.fixture(scope="module")
def copied(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The examples, copied where the checkout (``benchmarks``, ``tests``) is not importable."""
    where = tmp_path_factory.mktemp("examples") / "patterns"
    shutil.copytree(EXAMPLES, where, ignore=shutil.ignore_patterns("__pycache__"))
    return where


@pytest.fixture(scope="module")
def run(port: int, copied: Path) -> Callable[..., str]:
    """``run(name, *args)``: the example's output, run from the copy against the server."""
    return lambda name, *extra: _run(copied, name, port, *extra)


def _run(where: Path, name: str, port: int, *extra: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, str(where / f"{name}.py"), "--port", str(port), "--cycles", "300",
         *extra],
        cwd=where, env=env, capture_output=True, text=True, timeout=90, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def _written(out: str, role: str) -> int:
    match = re.search(rf"  {role}: ChannelStatistics\(.*?, written=(\d+)", out)
    assert match is not None, out
    return int(match.group(1))


@pytest.mark.parametrize("layout", ["process", "thread"])
@pytest.mark.parametrize("pattern", ["buffered", "sampled", "loop"])
def test_send_example_sends_through_the_bridge(pattern: str, layout: str,
                                               run: Callable[..., str]) -> None:
    out = run("send", pattern, "--layout", layout)
    assert re.search(r"releases, \d+ missed; lateness p50", out), out
    assert _written(out, "out") > 0
    # the default layout says where the loop ran, as recorded inside the loop process
    assert ("loop process: SCHED" in out) == (layout == "process"), out


def test_naive_send_example_runs_in_process(run: Callable[..., str]) -> None:
    out = run("send", "naive")
    assert _written(out, "out") > 0
    assert "loop process:" not in out


@pytest.mark.parametrize("layout", ["process", "thread"])
@pytest.mark.parametrize("name", ["receive_nonblocking", "receive_blocking"])
def test_receive_example_reads_what_its_publisher_sends(name: str, layout: str,
                                                        run: Callable[..., str]) -> None:
    out = run(name, "--layout", layout)
    assert _written(out, "in") > 0, out
    if name == "receive_blocking":  # the helper clamped what the loop saw
        match = re.search(r"loop saw values in \[([-+.\d]+), ([-+.\d]+)\]", out)
        assert match is not None, out
        assert -0.5 <= float(match.group(1)) <= float(match.group(2)) <= 0.5


def test_receive_naive_example_reads_what_its_publisher_sends(run: Callable[..., str]) -> None:
    out = run("receive_naive")
    assert _written(out, "in") > 0, out


def test_separate_process_example_crosses_shared_memory_both_ways(
        run: Callable[..., str]) -> None:
    out = run("separate_process")
    assert re.search(r"loop process: \d+ releases", out), out
    assert "ring dropped 0, loop exit code 0" in out, out
    assert _written(out, "in") > 0
    assert _written(out, "out") > 0  # the loop's values left through this process's bridge
