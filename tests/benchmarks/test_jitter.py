"""``python -m benchmarks.jitter run``: runs end to end, and its statistics say what they claim.

Timing is not asserted (this box may be loaded); what is: every scenario ran in its own
processes with the same treatment as the reference, the report has its rows, and the paired
statistics compare rounds with rounds.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from benchmarks.jitter import cli as jitter
from benchmarks.jitter.config import RunStats, Scenario, ScenarioResult


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
    reference, *others = results
    # interleaved: the reference before every scenario and once more at the end
    assert [r.seq for r in reference.runs] == [0, 2, 4, 6], lines
    assert sorted(run.seq for res in others for run in res.runs
                  if run.seq is not None) == [1, 3, 5]
    for res in results:
        assert len(res.runs) == (4 if res is reference else 1), lines
        assert res.runs[0].samples >= 1
        steal = res.runs[0].steal_ms
        assert steal is not None
        assert steal >= 0
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


def _run(p99: float, rnd: int, seq: int | None) -> RunStats:
    return RunStats(10.0, p99, p99, 100, 0, rnd, seq)


def test_interleaved_pairing_uses_the_reference_runs_next_to_each_scenario() -> None:
    ref = ScenarioResult(Scenario("reference", "all", "Reference"))
    ref.runs = [_run(100.0, 0, 0), _run(300.0, 0, 2), _run(5000.0, 0, 4)]
    near_calm = _result("a", [])
    near_calm.runs = [_run(220.0, 0, 1)]  # between 100 and 300: compared with 200
    near_burst = _result("b", [])
    near_burst.runs = [_run(2700.0, 0, 3)]  # between 300 and 5000: compared with 2650
    assert near_calm.paired_delta(ref) == 20.0
    assert near_burst.paired_delta(ref) == 50.0
    legacy = _result("c", [])
    legacy.runs = [_run(1900.0, 0, None)]  # no position recorded: the round's mean, 1800
    assert legacy.paired_delta(ref) == 100.0


def test_round_order_interleaves_the_reference_and_rotates() -> None:
    config = jitter.JitterConfig(only=("receive-nonblocking", "send-buffered"))
    names = [s.name for s in config.scenarios()]
    assert names == ["reference", "receive-nonblocking", "send-buffered"]
    assert config.round_order(0) == [0, 1, 0, 2, 0]
    assert config.round_order(1) == [0, 2, 0, 1, 0]
    plain = dataclasses.replace(config, interleave=False)
    assert plain.round_order(0) == [0, 1, 2]
    assert plain.round_order(1) == [1, 2, 0]
    gil = jitter.JitterConfig(suite="gil")  # a reference per switch interval: not interleaved
    assert gil.round_order(0) == list(range(len(gil.scenarios())))


def test_pool_reads_old_and_interleaved_runs(tmp_path: Path) -> None:
    """Runs written before ``seq`` and ``steal_ms`` existed still pool with new ones."""
    def dump(path: Path, ref_runs: list[dict[str, Any]], runs: list[dict[str, Any]]) -> None:
        scenario = {"group": "g", "label": "x", "switch_interval": None}
        path.write_text(json.dumps({"results": [
            {"scenario": {**scenario, "name": "reference"}, "runs": ref_runs},
            {"scenario": {**scenario, "name": "receive-blocking"}, "runs": runs}]}))

    def raw(p99: float, rnd: int, **extra: Any) -> dict[str, Any]:
        return {"p50_us": 10.0, "p99_us": p99, "max_us": p99, "samples": 100, "missed": 0,
                "round": rnd, **extra}

    dump(tmp_path / "old.json", [raw(100.0, 0)], [raw(150.0, 0)])  # +50
    dump(tmp_path / "new.json",
         [raw(100.0, 0, seq=0, steal_ms=0.0), raw(900.0, 0, seq=2, steal_ms=20.0),
          raw(100.0, 0, seq=4, steal_ms=0.0)],
         [raw(510.0, 0, seq=1, steal_ms=0.0), raw(90.0, 0, seq=5, steal_ms=0.0)])  # +10, -10
    table = jitter.pooled_deltas([tmp_path / "old.json", tmp_path / "new.json"])
    row = next(line for line in table.splitlines() if line.startswith("| receive-blocking"))
    cells = row.strip("| ").split(" | ")
    assert cells[2:5] == ["3", "+0", "+10"]  # rounds, d p50, median d p99
    # at equal steal, from the new file only: 510 vs refs at steal 0 (100, 100) and 20 (900),
    # 3 nearest = all three, median 100 -> +410; 90 -> -10; median of the two: +200
    assert cells[8] == "+200"


def test_pool_refuses_a_file_that_is_not_a_run_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"results": [{"scenario": {"name": "reference"}}]}')
    for path, expected in ((bad, "bad.json: not the JSON of a `python -m benchmarks.jitter "
                                 "run` run"),
                           (tmp_path / "missing.json", "No such file")):
        with pytest.raises(SystemExit) as exc:
            jitter.main(["pool", str(path)])
        message = str(exc.value.code)
        assert message.startswith("pool: ")
        assert expected in message
        assert "\n" not in message


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
