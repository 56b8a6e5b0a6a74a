"""Fixtures of the CSP primitives' tests: ``frequent_switches`` for the thread tests.

Helpers that tests import live in top-level modules (``tests/waiting.py``), never here
(tests never import ``conftest``: tests/architecture/test_test_imports.py).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest


@pytest.fixture
def frequent_switches() -> Iterator[None]:
    """Ask for a GIL hand-off every microsecond so that operations really interleave."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        yield
    finally:
        sys.setswitchinterval(old)
