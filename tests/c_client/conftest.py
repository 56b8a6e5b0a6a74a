"""The C client (clients/c) built once per session, and its example programs run as processes.

The build is skipped with the reason when this machine cannot build C (no cmake, compiler or
libraries), unless ``RLBRIDGE_TEST_REQUIRE_C=1`` (CI) makes that a failure.
``RLBRIDGE_C_BUILD`` names a build directory to reuse (scripts/test.sh builds ``build/c``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from c_programs import CProcess

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "clients" / "c"
REQUIRE = os.environ.get("RLBRIDGE_TEST_REQUIRE_C") == "1"


def _unavailable(why: str) -> None:
    if REQUIRE:
        pytest.fail(f"the C client cannot be built ({why}) and RLBRIDGE_TEST_REQUIRE_C=1")
    pytest.skip(f"the C client cannot be built here: {why} "
                "(apt-get install cmake gcc libmsgpack-dev libsodium-dev libssl-dev)")


@pytest.fixture(scope="session")
def c_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The directory holding ``rlb_pub`` and ``rlb_sub``, built with -Werror."""
    missing = [tool for tool in ("cmake", "cc") if shutil.which(tool) is None]
    if missing:
        _unavailable(f"{' and '.join(missing)} not installed")
    build = Path(os.environ.get("RLBRIDGE_C_BUILD") or tmp_path_factory.mktemp("c-build"))
    configure = subprocess.run(["cmake", "-S", str(SOURCE), "-B", str(build)],
                               capture_output=True, text=True, check=False)
    if configure.returncode != 0:
        output = configure.stdout + configure.stderr
        if "not found" in output:
            _unavailable(next(line.strip() for line in output.splitlines() if "not found" in line))
        pytest.fail(f"cmake could not configure clients/c:\n{output[-3000:]}")
    compiled = subprocess.run(["cmake", "--build", str(build), "-j", "2"],
                              capture_output=True, text=True, check=False)
    if compiled.returncode != 0:
        pytest.fail(f"clients/c does not build:\n{(compiled.stdout + compiled.stderr)[-3000:]}")
    return build


@pytest.fixture
def c_processes() -> Iterator[list[CProcess]]:
    """Every example program a test starts; killed at teardown if still running."""
    procs: list[CProcess] = []
    yield procs
    for p in procs:
        p.close()
