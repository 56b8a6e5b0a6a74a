"""The words every benchmark module shares: sides, parameters, roles, and a run's failures.

They sit apart from the parent's process handling and the children's entry point, which both
use them, so that neither side imports the other.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal

Side = Literal["a", "b"]
Params = dict[str, Any]
Role = Callable[[Params], None]


class BenchError(RuntimeError):
    """A benchmark run failed (a child died, timed out, or reported an error)."""


class Skipped(Exception):
    """A row cannot be measured here (an optional package is missing); the reason is printed."""


def select_cases(cases: Sequence[Any], only: Sequence[str]) -> list[Any]:
    """The rows whose ``key`` is in ``only`` (every row if empty); an unknown key is an error."""
    unknown = set(only) - {c.key for c in cases}
    if unknown:
        raise BenchError(f"unknown row key(s) {', '.join(sorted(unknown))}; the rows are "
                         f"{', '.join(c.key for c in cases)}")
    return [c for c in cases if not only or c.key in only]
