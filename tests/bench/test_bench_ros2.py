"""Smoke test of ``rlbridge bench ros2``: a tiny run through real rclpy and bridge processes.

Nothing is timed or compared (figures on a shared CI machine mean nothing): what is checked is
that the baseline and bridge rows in both directions run end to end in separate processes, that
the report has both tables with numbers in them, that ``--out`` writes its own section, that bad
options are one line, and that no worker process is left behind.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from proc_children import children
from rlbridge.bench.cli import bench_app

pytestmark = [pytest.mark.ros2, pytest.mark.timeout(120)]


def _table_rows(text: str) -> dict[str, list[list[str]]]:
    rows: dict[str, list[list[str]]] = {}
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("| path"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            rows.setdefault(cells[0], []).append(cells[1:])
    return rows


def test_bench_ros2_runs_baseline_and_both_directions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(1 + (os.getpid() + 50) % 100))
    out = tmp_path / "ros2.md"
    out.write_text("# ROS 2\n\nhand-written text\n")
    before = children()
    result = CliRunner().invoke(bench_app, [
        "ros2", "--count", "60", "--seconds", "0.3", "--repeats", "1",
        "--only", "rclpy,in-udp,out-tcp", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _table_rows(result.output)
    for label in ("rclpy node -> rclpy node, 1 hop", "rclpy node -> bridge -> SDK, UDP",
                  "SDK -> bridge -> rclpy node, TCP"):
        latency, throughput = rows[label]
        assert float(latency[0].replace(",", "")) > 0, latency  # p50 us
        assert float(throughput[1].replace(",", "")) > 0, throughput  # received values/s
    assert rows["rclpy node -> rclpy node, 1 hop"][0][3] == "1.00"  # its own ratio
    text = out.read_text()
    assert text.startswith("# ROS 2\n\nhand-written text\n")
    assert text.count("<!-- bench:ros2 begin -->") == 1
    assert "Command: `rlbridge bench ros2 --count 60" in text
    assert "discovery LOCALHOST" in text
    assert children() <= before


@pytest.mark.parametrize(("args", "phrase"), [
    (["--modes", "speed"], "--modes takes latency and/or throughput"),
    (["--only", "rclpy,nope"], "unknown row key(s) nope"),
])
def test_bench_ros2_bad_options_are_one_line(tmp_path: Path, args: list[str],
                                             phrase: str) -> None:
    result = CliRunner().invoke(bench_app, ["ros2", *args, "--out", str(tmp_path / "x.md")])
    assert result.exit_code == 1
    assert phrase in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "x.md").exists()
