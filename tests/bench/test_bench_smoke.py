"""Smoke test of ``rlbridge bench throughput`` and ``latency``: tiny runs, output shape only.

Nothing here is timed or compared: on a shared CI machine the figures mean nothing. What is
checked is that every kind of row runs end to end in real processes (rlbridge over both
transports, the raw UDP baseline, ZeroMQ and Zenoh or their "skipped" line), that the markdown
report has its table and targets, that ``--out`` replaces only its own section, and that no
worker process is left behind.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from proc_children import children
from rlbridge.bench import baselines
from rlbridge.bench.cli import bench_app
from rlbridge.bench.common import markdown_table, percentile, write_section

pytestmark = pytest.mark.timeout(120)


def _rows(text: str) -> dict[str, list[str]]:
    """Markdown table rows by their path label (first cell, or second after a rate)."""
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and not set(line) <= set("|-: "):
            key = cells[1] if cells[0].endswith("Hz") else cells[0]
            rows[key] = cells
    return rows


def test_throughput_runs_every_kind_of_row(tmp_path: Path) -> None:
    out = tmp_path / "bench.md"
    out.write_text("# Benchmarks\n\nhand-written text\n")
    before = children()
    result = CliRunner().invoke(bench_app, [
        "throughput", "--count", "3000", "--seconds", "1", "--repeats", "1", "--batch", "256",
        "--only", "udp,zmq,zenoh,rlb-udp-1,rlb-udp-1-single,rlb-tcp-batch", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _rows(result.output)
    for label in ("raw UDP socket, 1 hop", "rlbridge UDP, write per value, bundles",
                  "rlbridge UDP, 1 value/datagram (bundles=False)",
                  "rlbridge TCP, write_many(256)"):
        assert float(rows[label][1].replace(",", "")) > 0, rows[label]
    for label in ("ZeroMQ PUB/SUB tcp, 1 hop", "Zenoh peer tcp, 1 hop"):
        assert rows[label][1].startswith("skipped: ") or float(rows[label][1].replace(",", ""))
    assert "Targets:" in result.output
    assert re.search(r"rlbridge UDP, write per value, bundles: .* x the raw UDP loop",
                     result.output)
    text = out.read_text()
    assert text.startswith("# Benchmarks\n\nhand-written text\n")
    assert text.count("<!-- bench:throughput begin -->") == 1
    assert "Command: `rlbridge bench throughput --count 3000" in text
    assert children() <= before


def test_latency_runs_every_kind_of_row(tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(baselines, "unavailable",
                        lambda kind: "pretend it is missing" if kind == "zmq" else None)
    out = tmp_path / "bench.md"
    result = CliRunner().invoke(bench_app, [
        "latency", "--count", "30", "--repeats", "1", "--rates", "1000",
        "--only", "udp,zmq,rlb-udp,rlb-udp-inline,rlb-tcp-nodelay", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _rows(result.output)
    assert rows["ZeroMQ PUB/SUB tcp, 1 hop"][2] == "skipped: pretend it is missing"
    for label in ("raw UDP socket, 1 hop", "rlbridge UDP", "rlbridge UDP, send(inline=True)",
                  "rlbridge TCP, nodelay"):
        cells = rows[label]
        p50, p99 = float(cells[2].replace(",", "")), float(cells[3].replace(",", ""))
        assert 0 < p50 <= p99, cells
        assert cells[-2] == "30", cells  # samples kept per run, after the warm-up
    assert "<!-- bench:latency begin -->" in out.read_text()


def test_throughput_flow_rows_add_up_and_lose_nothing(tmp_path: Path) -> None:
    result = CliRunner().invoke(bench_app, [
        "throughput", "--count", "20000", "--seconds", "1", "--repeats", "1",
        "--only", "rlb-tcp-slow-flow,rlb-udp-batch", "--out", str(tmp_path / "b.md")])
    assert result.exit_code == 0, result.output
    assert re.search(r"flow control: 0 values lost over 1 runs", result.output), result.output
    for line in result.output.splitlines():
        stages = re.search(r"\| ([^|]*end to end: ([\d,]+)) \|", line)
        if stages:  # every stage's count adds up to the end-to-end loss, none below zero
            counts = {k: int(v.replace(",", "")) for k, v in
                      re.findall(r"([^,:]+(?:\([^)]*\))?): ([\d,]+)", stages.group(1))}
            end = counts.pop(" end to end", counts.pop("end to end", 0))
            assert sum(counts.values()) == end, line
            assert all(v >= 0 for v in counts.values()), line


def test_latency_idle_rows_report_cpu(tmp_path: Path) -> None:
    out = tmp_path / "bench.md"
    result = CliRunner().invoke(bench_app, [
        "latency", "--count", "30", "--repeats", "1", "--rates", "1000", "--idle", "park,spin",
        "--only", "rlb-udp,rlb-udp-spin", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _rows(result.output)
    assert float(rows["rlbridge UDP, idle=spin"][-4]) >= 0  # CPU % of the publisher
    assert "<!-- bench:latency-idle begin -->" in out.read_text()
    bad = CliRunner().invoke(bench_app, ["latency", "--idle", "nap", "--out", str(out)])
    assert bad.exit_code == 2
    assert "unknown idle strategy 'nap'" in bad.output


def test_latency_stages_probe_every_stage(tmp_path: Path) -> None:
    out = tmp_path / "bench.md"
    result = CliRunner().invoke(bench_app, [
        "latency", "--stages", "--seconds", "0.05", "--repeats", "1", "--rates", "1000",
        "--idle", "park,busy", "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _rows(result.output)
    total = rows["total: `write` -> `read` returns"][1:]
    assert len(total) == 2  # a column per strategy
    assert all(float(x.replace(",", "")) > 0 for x in total)
    probed = [label for label in rows if label.startswith(("`write`", "->"))]
    assert len(probed) == 8  # every stage has a figure, none missing a probe
    assert all(x != "-" for label in probed for x in rows[label][1:])
    assert "<!-- bench:latency-stages begin -->" in out.read_text()


def test_feedback_runs(tmp_path: Path) -> None:
    out = tmp_path / "bench.md"
    result = CliRunner().invoke(bench_app, [
        "feedback", "--repeats", "1", "--seconds", "0.5", "--only", "flood", "--out", str(out)])
    assert result.exit_code == 0, result.output
    row = _rows(result.output)["UDP flood, no limit"]
    assert row[5] == "1/1", row  # the publisher's reported counts equal the server's
    assert "<!-- bench:feedback begin -->" in out.read_text()


def test_write_section_replaces_only_its_own_section(tmp_path: Path) -> None:
    path = tmp_path / "b.md"
    write_section(path, "a", "first")
    write_section(path, "b", "other")
    write_section(path, "a", "second")
    text = path.read_text()
    assert "first" not in text
    assert text.index("second") < text.index("other")


def test_percentile_and_table_helpers() -> None:
    assert percentile([1.0, 2.0, 3.0, 4.0], 50) == 2.5
    assert percentile([5.0], 99) == 5.0
    assert markdown_table(["a", "b"], [["x", "1"]]).splitlines()[1] == "|---|---:|"


def test_unknown_row_key_is_one_line_error(tmp_path: Path) -> None:
    result = CliRunner().invoke(bench_app, ["latency", "--only", "nope", "--out",
                                            str(tmp_path / "b.md")])
    assert result.exit_code == 1
    assert "unknown row key(s) nope" in result.output
    assert not (tmp_path / "b.md").exists()
