"""What every benchmark imports, from one place: the modules below, re-exported.

* :mod:`~rlbridge.bench.base`: sides, parameters, roles, :class:`BenchError`, row selection;
* :mod:`~rlbridge.bench.workers`: the parent side (links, worker processes, CPU accounting);
* :mod:`~rlbridge.bench.child`: the child side (entry point, commands, pacing, the server);
* :mod:`~rlbridge.bench.stats` and :mod:`~rlbridge.bench.report`: figures and reports.

The benchmarks name these through ``rlbridge.bench.common`` so that each of them reads as one
import of the shared vocabulary; the split is for the reader of the machinery, not its users.
"""

from __future__ import annotations

from rlbridge.bench.base import BenchError, Params, Role, Side, Skipped, select_cases
from rlbridge.bench.child import (
    ROLES,
    WORKER_MODULES,
    Control,
    Tally,
    emit,
    flood,
    hold,
    paced,
    server_role,
    wait_for_go,
    worker_main,
)
from rlbridge.bench.report import (
    cpu_model,
    fmt,
    machine_info,
    markdown_table,
    progress,
    report_header,
    write_section,
)
from rlbridge.bench.stats import median, percentile, ratio
from rlbridge.bench.workers import (
    CLK_TCK,
    STARTUP_S,
    Flow,
    Link,
    LoopbackLink,
    ProcessGroup,
    Worker,
    cpu_seconds,
    rlbridge_flow,
    run_flow,
    start_server,
)

__all__ = [
    "CLK_TCK", "ROLES", "STARTUP_S", "WORKER_MODULES", "BenchError", "Control", "Flow", "Link",
    "LoopbackLink", "Params", "ProcessGroup", "Role", "Side", "Skipped", "Tally", "Worker",
    "cpu_model", "cpu_seconds", "emit", "flood", "fmt", "hold", "machine_info", "markdown_table",
    "median", "paced", "percentile", "progress", "ratio", "report_header", "rlbridge_flow",
    "run_flow",
    "select_cases", "server_role", "start_server", "wait_for_go", "worker_main", "write_section",
]
