"""The README's coupling-pattern example runs as printed, as a script of its own.

It is the first code a user copies for a fast loop, and the default layout spawns a process
that imports the user's script: the example must work as a file, main guard included.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from rlbridge.csp.shm import ShmLink
from rlbridge.server import ServerConfig, ServerThread

README = Path(__file__).resolve().parents[2] / "README.md"


def _pattern_example() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    found = [b for b in blocks if "patterns.receive_nonblocking" in b]
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
