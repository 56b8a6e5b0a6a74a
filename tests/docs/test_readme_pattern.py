"""The README's coupling-pattern example runs as printed, as a script of its own.

It is the first code a user copies for a fast loop, and the default layout spawns a process
that imports the user's script: the example must work as a file, main guard included.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rlbridge import ShmLink
from rlbridge.server import ServerConfig, ServerThread
from waiting import wait_until

README = Path(__file__).resolve().parents[2] / "README.md"


def _pattern_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    found = [b for b in blocks if "receive_nonblocking(" in b]
    assert len(found) == 1, "the README should have exactly one coupling-pattern example"
    return found[0]


@pytest.mark.skipif(not ShmLink.supported(), reason="the default layout needs x86")
def test_readme_pattern_example_runs_as_a_script(tmp_path: Path) -> None:
    code = _pattern_example()
    assert 'Bridge.connect("192.168.1.10", 7411' in code
    script = tmp_path / "tracker.py"
    with ServerThread(ServerConfig(port=0)) as srv:
        script.write_text(code.replace('"192.168.1.10", 7411', f'"127.0.0.1", {srv.port}')
                          .replace("cycles=5000", "cycles=300"))
        proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                              text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    p99, *policy, y = proc.stdout.split()
    assert int(p99) > 0
    assert policy[0].startswith("SCHED_")  # the loop process said what it ran with
    assert float(y) == 0.0  # nobody published: the filter stayed at the initial value


def _group_alive(pgid: int) -> list[str]:
    """Processes of group ``pgid`` that still run (zombies wait for init: they do not run)."""
    ps = subprocess.run(["ps", "-ww", "-o", "pid=,stat=,args=", "-g", str(pgid)],
                        capture_output=True, text=True, check=False, timeout=30)
    return [line for line in ps.stdout.splitlines() if line.split()[1][0] != "Z"]


@pytest.mark.skipif(not ShmLink.supported(), reason="the default layout needs x86")
@pytest.mark.parametrize("after", [0.0, 1.0])
def test_ctrl_c_on_the_readme_pattern_example_stops_quietly_with_130(
        tmp_path: Path, after: float) -> None:
    """A real SIGINT to the whole process group, as a terminal's Ctrl-C sends it: while the
    loop process starts (``after`` 0) and while it runs."""
    code = _pattern_example()
    script = tmp_path / "tracker.py"
    with ServerThread(ServerConfig(port=0)) as srv:
        script.write_text(
            code.replace('"192.168.1.10", 7411', f'"127.0.0.1", {srv.port}')
            .replace("cycles=5000", "cycles=10_000_000")  # hours: only Ctrl-C ends it
            .replace("        try:\n", "        print(loop.link.name, flush=True)\n        try:\n"))
        proc = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                start_new_session=True)
        try:
            assert proc.stdout is not None
            segment = proc.stdout.readline().strip()
            assert segment, proc.communicate(timeout=30)
            wait_until(lambda: loop_is_running(proc.pid), "the loop process to start",
                       timeout=60, interval=0.1)
            time.sleep(after)
            os.killpg(proc.pid, signal.SIGINT)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert err == ""  # no traceback, neither the loop process's nor the script's
    assert out == ""
    assert not (Path("/dev/shm") / segment).exists(), f"{segment} left in /dev/shm"
    alive: list[str] = []

    def group_gone() -> bool:
        alive[:] = _group_alive(proc.pid)
        return not alive

    wait_until(group_gone, lambda: f"the process group to end; still running: {alive}",
               interval=0.1)


def loop_is_running(pgid: int) -> bool:
    """The loop process (a spawned interpreter) is up in the group."""
    return any("spawn_main" in line for line in _group_alive(pgid))
