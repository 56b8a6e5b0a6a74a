"""Smoke test of ``python -m benchmarks.soak``: a tiny run, report shape only.

Nothing is timed (the figures of a shared CI machine mean nothing). Checked: the soak has one
row per interval, the loss-by-stage table, ``--out`` gets the section, and no process is left
behind.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from benchmarks import soak
from proc_children import children

pytestmark = pytest.mark.timeout(120)


def test_soak_has_a_row_per_interval(tmp_path: Path) -> None:
    out = tmp_path / "load.md"
    before = children()
    result = CliRunner().invoke(soak.app, [
        "--minutes", "0.05", "--interval-s", "1", "--clients", "2", "--channels", "2",
        "--rate", "20", "--processes", "1", "--udp-receive-buffer", str(1 << 20),
        "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = [line for line in result.output.splitlines()
            if re.match(r"\| \d+\.\d\d \|", line)]  # "| 0.02 | ...": t (min)
    assert len(rows) == 3, result.output
    assert "Server RSS from the end of the first interval" in result.output
    # Loss by stage, each from its own witness, and what the server's socket was granted.
    for stage in ("lost at the publisher", "lost at hop 1", "dropped by the server",
                  "lost at hop 2", "in flight at the end"):
        assert f"| {stage}" in result.output, stage
    assert "Server's UDP receive buffer: asked 1,048,576 bytes, got " in result.output
    assert "<!-- bench:soak begin -->" in out.read_text()
    assert children() <= before
