"""``rlbridge bench latency --transport/--delay/--loss``: one stream across the emulated link.

Without those options ``rlbridge bench latency`` keeps measuring SDK -> server -> SDK on
loopback next to its baselines (``bench/latency.py``). With them, the thesis's set-up: bridge
server and middleware endpoint in namespace A, the SDK client in namespace B, the relay of
``rlbridge.netem`` delaying/dropping the data direction (``bench/netpath.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from rlbridge.bench.common import BenchError, Link, fmt, markdown_table
from rlbridge.bench.netpath import PriorityLink, StreamSpec, measure_stream
from rlbridge.bench.scenarios import TRANSPORTS, summarise

TRANSPORT_KEYS = tuple(t.key for t in TRANSPORTS)


def csv_path(base: Path, key: str, many: bool) -> Path:
    """``base`` for one transport; ``<stem>-<transport><suffix>`` when several share it."""
    return base.with_name(f"{base.stem}-{key}{base.suffix}") if many else base


def run(*, transports: Sequence[str], delay_ms: float, loss_pct: float, rate_hz: float,
        count: int, direction: str, csv: Path | None, seed: int = 1, rt_priority: int = 5,
        echo: Callable[[str], None] = print) -> str:
    """Measure each transport once over one link; returns the markdown summary table.

    ``rt_priority``: SCHED_FIFO priority of the measured processes (``PriorityLink``; 0 off).
    """
    from rlbridge.netem import EmulatedLink, emulator_unavailable_reason

    unknown = [t for t in transports if t not in TRANSPORT_KEYS]
    if unknown:
        raise BenchError(f"unknown transport {unknown[0]!r}; use one of "
                         f"{', '.join(TRANSPORT_KEYS)}")
    if direction not in ("down", "up"):
        raise BenchError(f"direction must be 'down' or 'up', got {direction!r}")
    reason = emulator_unavailable_reason()
    if reason is not None:
        raise BenchError(f"the network emulator cannot run here: {reason}")
    rows = []
    period_ms = 1000.0 / rate_hz
    with EmulatedLink(delay_ms=delay_ms, loss_pct=loss_pct, seed=seed, relay_rt_priority=10,
                      direction="a_to_b" if direction == "down" else "b_to_a") as emulated:
        link: Link = PriorityLink(emulated, rt_priority) if rt_priority else emulated
        for t in (t for t in TRANSPORTS if t.key in transports):
            echo(f"  {t.label}: {count} samples at {rate_hz:g} Hz, {direction}")
            res = measure_stream(link, StreamSpec(direction, t.transport, t.nodelay, rate_hz,
                                                  count))
            s = summarise(res.latencies_ms, delay_ms=delay_ms, period_ms=period_ms)
            if csv is not None:
                path = csv_path(csv, t.key, len(transports) > 1)
                path.write_text("\n".join(res.csv_rows()) + "\n")
                echo(f"  wrote {path}")
            rows.append([t.label, fmt(s.p50, 2), fmt(s.p99, 2), fmt(s.max, 2),
                         f"{s.lost} / {s.samples}", f"{s.delayed}", f"{fmt(s.within_pct, 1)} %"])
    title = (f"Link: delay {delay_ms:g} ms, loss {loss_pct:g} % ({direction}, data direction "
             f"impaired), {rate_hz:g} Hz, {count} samples\n\n")
    return title + markdown_table(["transport", "p50 ms", "p99 ms", "max ms", "lost",
                                   "delayed > 1 period", "in [d, d+1 ms]"], rows) + "\n"
