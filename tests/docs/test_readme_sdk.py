"""The README's SDK examples run as printed against ``rlbridge serve``: scripts/readme_example.py.

scripts/test.sh runs the same script on Python 3.10, 3.11, 3.12 and 3.13, each in a fresh venv
with a plain ``pip install .`` (what a user does); this test runs it in the test venv, so a
change to the README's examples or to the SDK that breaks them fails the suite on any Python.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "readme_example.py"


def test_readme_examples_run_against_rlbridge_serve() -> None:
    proc = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True,
                          timeout=180, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "control code: read set-point 1.0 over UDP, published angle 0.5" in proc.stdout
    assert "coupling pattern: " in proc.stdout
