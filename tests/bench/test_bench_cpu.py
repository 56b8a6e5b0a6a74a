"""Smoke test of ``rlbridge bench cpu``: a tiny run, report shape only (nothing timed)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from proc_children import children
from rlbridge.bench.cli import bench_app

pytestmark = pytest.mark.timeout(120)


def test_cpu_bench_reports_every_row(tmp_path: Path) -> None:
    out = tmp_path / "bench.md"
    before = children()
    result = CliRunner().invoke(bench_app, [
        "cpu", "--channels", "3", "--rate", "100", "--seconds", "0.5", "--repeats", "1",
        "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = {line.split("|")[1].strip(): line for line in result.output.splitlines()
            if line.startswith(("| bundled", "| inline", "| single", "| send loop"))}
    assert set(rows) == {"bundled", "inline", "single", "send loop"}
    for row in rows.values():
        assert row.split("|")[2].strip() == "150"  # 3 channels x 100 Hz x 0.5 s
    assert "<!-- bench:cpu begin -->" in out.read_text()
    assert children() == before
