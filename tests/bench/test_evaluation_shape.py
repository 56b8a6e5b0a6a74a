"""The thesis's network findings hold across the emulated link (short CI version).

Needs root and network namespaces (marked ``netem``); elsewhere it skips and prints why. Each
check is one short 100 Hz stream through the real bridge server and SDK client in two
namespaces, with the measured processes at a real-time priority (``PriorityLink``) so that a
loaded machine does not pass for a slow network. The bounds are the issue's: shapes, not
timings of this machine.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from rlbridge.bench.cli import bench_app
from rlbridge.bench.netpath import PriorityLink, StreamSpec, measure_stream
from rlbridge.bench.scenarios import summarise
from rlbridge.netem import EmulatedLink, emulator_unavailable_reason

UNAVAILABLE = emulator_unavailable_reason()
pytestmark = [pytest.mark.netem, pytest.mark.timeout(120),
              pytest.mark.skipif(UNAVAILABLE is not None,
                                 reason=f"network emulator unavailable: {UNAVAILABLE}")]

COUNT = 200
PERIOD_MS = 10.0


def _stream(delay_ms: float, loss_pct: float, transport: str, nodelay: bool) -> list[float | None]:
    with EmulatedLink(delay_ms=delay_ms, loss_pct=loss_pct, direction="a_to_b", seed=3,
                      relay_rt_priority=10, max_lifetime_s=120.0) as link:
        res = measure_stream(PriorityLink(link, 5),
                             StreamSpec("down", transport, nodelay, 100.0, COUNT))
        return res.latencies_ms


def test_udp_at_one_percent_loss_loses_samples_but_delays_none() -> None:
    lat = _stream(0.0, 1.0, "udp", False)
    s = summarise(lat, delay_ms=0.0, period_ms=PERIOD_MS)
    print(f"UDP 1 % loss: p50 {s.p50:.2f} p99 {s.p99:.2f} max {s.max:.2f} lost {s.lost}")
    assert s.p99 <= 0.0 + 2.0, f"UDP p99 {s.p99:.2f} ms at 1 % loss is not within delay + 2 ms"
    assert s.lost <= COUNT // 10


def test_tcp_loses_nothing_at_one_percent_loss() -> None:
    lat = _stream(0.0, 1.0, "tcp", False)
    s = summarise(lat, delay_ms=0.0, period_ms=PERIOD_MS)
    print(f"TCP+Nagle 1 % loss: p50 {s.p50:.2f} p99 {s.p99:.2f} lost {s.lost} "
          f"delayed {s.delayed}")
    assert s.lost == 0, "TCP lost samples"


def test_tcp_nagle_is_above_the_link_delay_at_7_5_ms() -> None:
    lat = _stream(7.5, 0.0, "tcp", False)
    s = summarise(lat, delay_ms=7.5, period_ms=PERIOD_MS)
    print(f"TCP+Nagle 7.5 ms: p50 {s.p50:.2f} p99 {s.p99:.2f} max {s.max:.2f} lost {s.lost}")
    assert s.lost == 0, "TCP lost samples"
    got = [x for x in lat if x is not None]
    assert min(got) >= 7.5, "a sample beat the emulated delay"
    assert s.p99 > 7.5 + 1.0, "TCP+Nagle stayed in the delay + 1 ms band: no Nagle stall seen"


def test_latency_cli_writes_one_csv_row_per_sample(tmp_path: Path) -> None:
    csv = tmp_path / "lat.csv"
    result = CliRunner().invoke(bench_app, ["latency", "--transport", "udp", "--delay", "3",
                                            "--count", "50", "--csv", str(csv)])
    assert result.exit_code == 0, result.output
    assert "| UDP |" in result.output
    lines = csv.read_text().splitlines()
    assert lines[0] == "seq,sent_ns,recv_ns,latency_ms"
    assert [int(line.split(",")[0]) for line in lines[1:]] == list(range(50))
    got = [float(line.split(",")[3]) for line in lines[1:] if line.split(",")[3]]
    assert got
    assert min(got) >= 3.0
