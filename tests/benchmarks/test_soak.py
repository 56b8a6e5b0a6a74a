"""Smoke test of ``python -m benchmarks.soak``: a tiny run, report shape only.

Nothing is timed (the figures of a shared CI machine mean nothing). Checked: the soak has one
row per interval, ``--out`` gets the section, and no process is left behind.
"""

from __future__ import annotations

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
        "--rate", "20", "--processes", "1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = [line for line in result.output.splitlines()
            if line.startswith("| ") and "t (min)" not in line and "---" not in line]
    assert len(rows) == 3, result.output
    assert "Server RSS from the end of the first interval" in result.output
    assert "<!-- bench:soak begin -->" in out.read_text()
    assert children() <= before
