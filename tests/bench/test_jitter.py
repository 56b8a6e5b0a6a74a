"""``rlbridge bench jitter``: runs end to end, and its statistics say what they claim.

Timing is not asserted (this box may be loaded); what is: every scenario ran in its own
processes with the same treatment as the reference, the report has its rows, and the paired
statistics compare rounds with rounds.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from rlbridge.bench import jitter
from rlbridge.bench.jitter_config import RunStats, Scenario, ScenarioResult


@pytest.fixture(autouse=True)
def _restore_switch_interval() -> Iterator[None]:
    before = sys.getswitchinterval()
    yield
    sys.setswitchinterval(before)


def test_jitter_benchmark_runs_end_to_end(tmp_path: Path) -> None:
    """Server, publisher and workers in their own processes; all gone afterwards."""
    config = jitter.JitterConfig(cycles=100, repeats=1, cpu=0,
                                 only=("receive-nonblocking", "receive-nonblocking-process",
                                       "send-loop-100-process"),
                                 out=tmp_path / "jitter.md", plot=None, command="test")
    lines: list[str] = []
    results = jitter.run(config, lines.append)
    assert [r.scenario.name for r in results] == [
        "reference", "receive-nonblocking-process", "receive-nonblocking",
        "send-loop-100-process"]
    for res in results:
        assert len(res.runs) == 1, lines
        assert res.runs[0].samples >= 1
        info = res.info[0]
        assert info["policy"]  # recorded from inside the HRT thread
        assert info["cpus"] == "0"  # every loop pinned alike, the reference's too
        assert "mlockall" in info
    own_process = results[-1].info[0]  # the pattern's default layout
    assert own_process["ring_dropped"] == 0
    assert own_process["out"]["written"] >= 1  # the loop's values left through the SDK process
    assert own_process["torn_reads"] == 0
    text = (tmp_path / "jitter.md").read_text()
    assert "| receive | Receive non-blocking (5.3), own process (default) |" in text
    assert "| receive | Receive non-blocking (5.3), in-process (layout='thread') |" in text
    assert (tmp_path / "jitter.patterns-only.json").exists()


def _result(name: str, p99_by_round: list[float]) -> ScenarioResult:
    res = ScenarioResult(Scenario(name, "g", name))
    res.runs = [RunStats(10.0, p99, p99, 100, 0, rnd) for rnd, p99 in enumerate(p99_by_round)]
    return res


def test_pairing_compares_each_round_with_its_own_reference() -> None:
    ref = _result("reference", [100.0, 5000.0, 200.0])
    pattern = _result("p", [110.0, 5100.0, 400.0])
    assert pattern.paired_delta(ref) == 100.0  # median of +10, +100, +200
    assert math.isclose(pattern.paired_ratio(ref), 1.1)  # median of 1.1, 1.02, 2.0
    assert pattern.rounds_met(ref) == (2, 3)  # +10 <= 20 us, +100 <= 500 us, +200 > 20 us
    partial = _result("q", [100.0])
    assert partial.rounds_met(ref) == (1, 1)  # only rounds measured by both count


def test_generated_section_is_replaced_and_prose_kept(tmp_path: Path) -> None:
    doc = tmp_path / "doc.md"
    markers = ("<!-- b -->", "<!-- e -->")
    doc.write_text("# Title\n\nprose before\n\n<!-- b -->\nold\n<!-- e -->\n\nprose after\n")
    jitter.write_section(doc, "<!-- b -->\nnew\n<!-- e -->\n", "Title", markers)
    expected = "# Title\n\nprose before\n\n<!-- b -->\nnew\n<!-- e -->\n\nprose after\n"
    assert doc.read_text() == expected


def test_percentile_and_target() -> None:
    assert jitter.percentile([], 99) == 0
    assert jitter.percentile(list(range(1, 101)), 99) == 99
    assert jitter.percentile(list(range(1, 101)), 50) == 50
    assert jitter.target_ok(100.0, 20.0)  # 20 us beats 10 % of 100 us
    assert not jitter.target_ok(1000.0, 101.0)
