"""``rlbridge bench`` writes nothing unasked: the report goes to stdout, a file only with --out.

Before, every subcommand's ``--out`` defaulted to a page under docs/: run from a checkout it
rewrote committed sections, run anywhere else it created a ``docs/`` folder in the user's
directory. The run here is real (a server, the baselines, the SDK rows) and tiny.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]


def test_a_latency_run_in_an_empty_directory_leaves_it_empty(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "rlbridge", "bench", "latency", "--seconds", "1", "--repeats",
         "1"], cwd=tmp_path, capture_output=True, text=True, timeout=220, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Command: `rlbridge bench latency" in proc.stdout  # the report, on stdout
    assert list(tmp_path.iterdir()) == []
