"""What both harnesses share: coverage for rlbridge's own code only, and the libFuzzer main.

Imported by the harness scripts (``python fuzz/fuzz_*.py``: this folder is on ``sys.path``);
without ``__main__`` (the test suite importing a harness) nothing is instrumented and atheris
need not be installed.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Callable
from typing import Any


def instrumented(main: bool) -> contextlib.AbstractContextManager[Any]:
    """Wrap the harness's rlbridge imports: instrumented when it runs as the fuzzer."""
    if not main:
        return contextlib.nullcontext()
    import atheris

    return atheris.instrument_imports(include=["rlbridge"])  # type: ignore[no-any-return]


def fuzz(one_input: Callable[[bytes], None]) -> None:
    """Run libFuzzer on ``one_input`` with the command line's flags and corpus folders."""
    import atheris

    logging.disable(logging.WARNING)  # every refused input logs a warning: millions of lines
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()
