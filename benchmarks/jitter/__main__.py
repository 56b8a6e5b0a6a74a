"""``python -m benchmarks.jitter``: the jitter and GIL suites, and their helper processes."""

from benchmarks.jitter.cli import app

app()
