"""Every server event counter is exported from the first scrape, at 0 (a real server, a real
scrape of /metrics), and every counter the source increments is one of them."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from test_stats_metrics import metrics_port, samples, scrape

from rlbridge.server import ServerThread
from rlbridge.server.context import EVENT_COUNTERS
from rlbridge.server.exposition import SERVER

SRC = Path(__file__).resolve().parents[2] / "src" / "rlbridge"


def metric_name(counter: str) -> str:
    return SERVER.get(counter, (f"rlbridge_{counter}_total", ""))[0]


def test_a_fresh_server_exports_every_event_counter_at_0(
        make_server: Callable[..., ServerThread]) -> None:
    srv = make_server(metrics_port=0)
    status, _type, text = scrape(metrics_port(srv))
    assert status == 200
    found = samples(text)
    missing = [metric_name(c) for c in EVENT_COUNTERS if metric_name(c) not in found]
    assert missing == []
    assert {metric_name(c): found[metric_name(c)] for c in EVENT_COUNTERS} == \
        {metric_name(c): 0 for c in EVENT_COUNTERS}
    for name in ("rlbridge_udp_bad_token_total", "rlbridge_udp_malformed_total",
                 "rlbridge_malformed_packets_total", "rlbridge_udp_bad_mac_total"):
        assert f"# TYPE {name} counter" in text
        assert found[name] == 0


def test_every_counter_the_server_increments_is_declared() -> None:
    """A new ``ctx.count("x")`` without "x" in EVENT_COUNTERS would appear only once it
    happened: this reads the source for every name counted."""
    source = "\n".join(p.read_text() for d in ("server", "adapters")
                       for p in (SRC / d).rglob("*.py"))
    counted = set(re.findall(r'\.count\(\s*"([a-z_]+)"', source))
    for first, second in re.findall(r'\.count\(\s*"([a-z_]+)"\s+if[^()]*(?:\([^()]*\)[^()]*)*'
                                    r'else\s+"([a-z_]+)"\)', source):
        counted |= {first, second}  # count("a" if ... else "b")
    # Sealed datagrams are counted as udp_<kind> of the DatagramRejected the seal raised.
    seal = (SRC / "wire" / "seal.py").read_text()
    kinds = re.findall(r'DatagramRejected\(\s*"([a-z_]+)"', seal)
    counted |= {f"udp_{kind}" for kind in kinds}
    assert {"udp_bad_mac", "tcp_rejected_records", "malformed", "rate_dropped"} <= counted
    assert counted - set(EVENT_COUNTERS) == set()
