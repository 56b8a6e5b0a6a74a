"""The fuzzing harnesses: the committed corpus replays cleanly, and a short atheris run finds
nothing (CI's bounded fuzzing; run longer by hand, see fuzz/*.py docstrings)."""

from __future__ import annotations

import importlib.util
import logging
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

FUZZ = Path(__file__).resolve().parents[2] / "fuzz"
HARNESSES = ["decoder", "server"]


def harness(name: str) -> ModuleType:
    if str(FUZZ) not in sys.path:  # the harnesses import their shared fuzz/_atheris.py
        sys.path.insert(0, str(FUZZ))
    spec = importlib.util.spec_from_file_location(f"fuzz_{name}", FUZZ / f"fuzz_{name}.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_SERVER = harness("server")
#: Whole seeds of the server corpus, minus their mode byte: valid and known-bad frames.
SEEDS_OF_FRAMES = [p.read_bytes()[1:] for p in sorted((FUZZ / "corpus" / "server").iterdir())]


@pytest.fixture(scope="module", autouse=True)
def _close_server_harness() -> Iterator[None]:
    yield
    _SERVER.close()


@pytest.mark.parametrize("name", HARNESSES)
def test_corpus_replays_cleanly(name: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.CRITICAL, logger="rlbridge.server")
    module = harness(name)
    seeds = sorted((FUZZ / "corpus" / name).iterdir())
    assert len(seeds) > 50, "the seed corpus is missing (python fuzz/make_corpus.py)"
    try:
        for seed in seeds:
            module.one_input(seed.read_bytes())
    finally:
        getattr(module, "close", lambda: None)()


@pytest.mark.parametrize("name", HARNESSES)
def test_short_fuzz_run(name: str, tmp_path: Path) -> None:
    pytest.importorskip("atheris")
    corpus = tmp_path / "corpus"
    shutil.copytree(FUZZ / "corpus" / name, corpus)  # new finds go here, not into the repo
    result = subprocess.run(
        [sys.executable, str(FUZZ / f"fuzz_{name}.py"), str(corpus), "-max_total_time=4",
         "-timeout=30", "-rss_limit_mb=1024", f"-artifact_prefix={tmp_path}/"],
        capture_output=True, text=True, timeout=100, check=False,
    )
    tail = "\n".join(result.stderr.splitlines()[-30:])
    assert result.returncode == 0, f"fuzzer found a crash:\n{tail}"
    assert "Done" in result.stderr, tail


@settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 255), st.lists(st.sampled_from(SEEDS_OF_FRAMES) | st.binary(max_size=64),
                                     max_size=8))
def test_server_harness_on_spliced_frames(mode: int, parts: list[bytes]) -> None:
    """Hypothesis' share (runs without atheris too): valid frames spliced with random bytes."""
    module = _SERVER
    module.one_input(bytes([mode]) + b"".join(parts))
