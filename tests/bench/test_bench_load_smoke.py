"""Smoke test of ``rlbridge bench load``: tiny runs, report shape only.

Nothing is timed or compared (the figures of a shared CI machine mean nothing). Checked: both
kinds of client (protocol-level and SDK) run end to end in real processes against a real server
process, every phase has its row, the slow consumer's counters are reported, ``--out`` gets the
section, and no process is left behind.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from proc_children import children
from rlbridge.bench.cli import bench_app

pytestmark = pytest.mark.timeout(120)


def _table(text: str) -> dict[str, list[str]]:
    """The phase table's rows by phase (the loss-by-stage table after it is not read)."""
    rows: dict[str, list[str]] = {}
    inside = False
    for line in text.splitlines():
        if line.startswith("| phase"):
            inside = True
        elif inside and not line.startswith("|"):
            break
        elif inside and "---" not in line:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            rows[cells[0]] = cells
    return rows


@pytest.mark.parametrize("client", ["raw", "sdk"])
def test_load_runs_every_phase(tmp_path: Path, client: str) -> None:
    out = tmp_path / "load.md"
    before = children()
    result = CliRunner().invoke(bench_app, [
        "load", "--clients", "3", "--channels", "2", "--rate", "20", "--processes", "2",
        "--phase-s", "1", "--slow-topics", "3", "--client", client, "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _table(result.output)
    assert set(rows) == {"base", "reader", "slow", "after"}
    for row in rows.values():
        assert float(row[3].replace(",", "")) > 0, row  # values delivered
    assert "Slow consumer (subscribed over TCP to 3 of the clients' topics" in result.output
    assert "Whole run: " in result.output
    assert re.search(r"of which [\d,]+ never reached the server", result.output), result.output
    assert re.search(r"\| lost at hop 1 \(server's receive buffer full: [\d,]+ datagrams "
                     r"dropped by the kernel", result.output), result.output
    assert "<!-- bench:load begin -->" in out.read_text()
    assert children() <= before
