"""Evaluation bookkeeping without a network: summaries, policy detection, report, CLI errors.

The numbers fed in are constructed so that each column has one right answer; the emulated runs
themselves are in ``test_evaluation_shape.py`` (root only).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import pytest
from typer.testing import CliRunner

from benchmarks.evaluation import policies
from benchmarks.evaluation import report as evaluation_report
from benchmarks.evaluation.sweep import EvalSettings, Evaluation, Row, ThroughputPoint, saturated
from rlbridge.bench.cli import bench_app
from rlbridge.bench.latency_link import csv_path
from rlbridge.bench.netpath import StreamResult, StreamSpec, _match
from rlbridge.bench.scenarios import summarise

pytestmark = pytest.mark.timeout(60)


def test_summarise_counts_loss_delay_and_the_thesis_band() -> None:
    lat: list[float | None] = [7.6, 7.9, None, 8.4, 30.0, 18.0, None, 7.5]
    s = summarise(lat, delay_ms=7.5, period_ms=10.0)
    assert (s.samples, s.received, s.lost) == (8, 6, 2)
    assert s.delayed == 2  # 30.0 and 18.0 are later than 7.5 + 10
    assert s.within_1ms == 4
    assert s.max == 30.0
    assert s.p50 == pytest.approx(8.15)
    empty = summarise([None, None], delay_ms=0.0, period_ms=10.0)
    assert empty.lost == 2
    assert math.isnan(empty.p50)
    assert math.isnan(empty.delayed_pct)


def test_match_maps_values_to_sequence_numbers_and_counts_duplicates() -> None:
    spec = StreamSpec(count=4)
    sent = {"stamps": [100, 200, 300, 400], "t_start": 0.0, "t_end": 0.04}
    got = {"values": [[100, 1_100], [300, 2_300], [300, 2_400], [400, 3_400]],
           "flagged": 1, "extra": {"sdk_lost": 1}}
    res = _match(spec, sent, got)
    assert res.recv_ns == [1_100, None, 2_300, 3_400]
    assert (res.lost, res.duplicates, res.flagged_old) == (1, 1, 1)
    assert res.csv_rows()[0] == "seq,sent_ns,recv_ns,latency_ms"
    assert res.csv_rows()[2] == "1,200,,"
    assert res.csv_rows()[3] == "2,300,2300,0.0020"
    with pytest.raises(Exception, match="never sent"):
        _match(spec, sent, {"values": [[999, 1]]})


def test_stream_spec_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="direction"):
        StreamSpec(direction="sideways")
    with pytest.raises(ValueError, match="transport"):
        StreamSpec(transport="sctp")


@dataclass(frozen=True)
class _Old:
    redundancy: int = 0


@dataclass(frozen=True)
class _New:
    redundancy: int = 0
    latest: bool = False
    max_age_ms: int = 0


class _Channel:
    def read_with_age(self, timeout: float) -> tuple[int, float]:
        return 0, 0.0


def test_policy_rows_are_detected_from_signatures() -> None:
    rows = {r.key: r for r in policies.policy_rows(7.5)}
    latest, k1, age = rows["tcpn-latest"], rows["udp-k1"], rows["udp-maxage"]
    assert policies.availability(k1, _Old, object) is None
    reason = policies.availability(latest, _Old, object)
    assert reason is not None
    assert "not available in this build" in reason
    assert "latest" in reason
    assert "read_with_age" in (policies.availability(age, _New, object) or "")
    assert policies.availability(age, _New, _Channel) is None
    assert rows["tcp-maxage"].age_limit_ms == 17.5


def _evaluation() -> Evaluation:
    ev = Evaluation()
    ev.note_load("start")
    lat: list[float | None] = [0.5, 0.6, None, 40.0]
    s = summarise(lat, delay_ms=0.0, period_ms=10.0)
    ev.rows = [Row("loss1", "udp", "UDP", "rlbridge", s, lat, bytes_per_value=75.0),
               Row("loss1", "tcpn-latest", "TCPn + latest", "policy",
                   note="not available in this build (no Policy(latest=...))")]
    ev.throughput = [ThroughputPoint("up", "udp", 100, 100.0, 99.0, 0, 200)]
    return ev


def test_report_has_tables_thesis_figures_guide_and_raw_summaries(tmp_path: Path) -> None:
    ev = _evaluation()
    out = tmp_path / "evaluation.md"
    figures, results = tmp_path / "figures" / "evaluation", tmp_path / "results"
    evaluation_report.write(ev, EvalSettings(count=4), ["python", "-m", "benchmarks.evaluation"],
                            out, figures, results)
    text = out.read_text()
    assert "| UDP | 0.60 | " in text
    assert "| 1 / 4 |" in text
    assert "~1 % lost (10 of 1000), none delayed" in text  # the thesis beside ours
    assert "not available in this build" in text
    assert "figure 5.1" in text
    assert "load average during the run" in text
    assert "(figures/evaluation/loss.png)" in text
    assert (figures / "loss.png").exists()
    data = json.loads((results / "summary.json").read_text())
    assert data["latency"][0]["lost"] == 1
    assert data["throughput"][0]["offered_hz"] == 100
    assert (results / "summary.csv").read_text().startswith("scenario,")


def test_saturation_rule_and_csv_names() -> None:
    assert not saturated(ThroughputPoint("up", "udp", 1000, 1000.0, 995.0, 0, 1000))
    assert saturated(ThroughputPoint("up", "udp", 1000, 1000.0, 800.0, 0, 1000))
    assert saturated(ThroughputPoint("up", "udp", 1000, 1000.0, 990.0, 20, 1000))
    assert not saturated(ThroughputPoint("up", "udp", 5000, 4533.0, 4496.0, 0, 5000))
    assert saturated(ThroughputPoint("up", "udp", 5000, 2400.0, 2400.0, 0, 5000))
    assert csv_path(Path("x/l.csv"), "udp", True) == Path("x/l-udp.csv")
    assert csv_path(Path("x/l.csv"), "udp", False) == Path("x/l.csv")


def test_latency_cli_rejects_an_unknown_transport_in_one_line() -> None:
    result = CliRunner().invoke(bench_app, ["latency", "--transport", "sctp"])
    assert result.exit_code == 1
    assert "unknown transport 'sctp'" in result.output


def test_stream_result_send_rate() -> None:
    res = StreamResult(StreamSpec(count=2), [1, 2], [3, None], 0.0, 0.5)
    assert res.send_rate == 4.0
    assert res.lost == 1
