"""``rlbridge netem`` commands, through typer's test runner."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar, cast

import pytest
from typer.testing import CliRunner

import rlbridge.netem
from rlbridge.netem import emulator_unavailable_reason
from rlbridge.netem.cli import netem_app
from rlbridge.netem.netns import list_namespaces

pytestmark = pytest.mark.timeout(60)

F = TypeVar("F", bound=Callable[..., None])


def needs_emulator(test: F) -> F:
    """Mark a test as needing real namespaces; it skips with the reason when unavailable."""
    return cast(F, pytest.mark.netem(pytest.mark.usefixtures("_require_emulator")(test)))


@pytest.fixture(scope="module")
def _require_emulator() -> None:
    reason = emulator_unavailable_reason()
    if reason is not None:
        pytest.skip(f"network emulator unavailable: {reason}")


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def test_commands_refuse_without_root_in_one_line(
    runner: CliRunner, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    for argv in (["check"], ["shell", "--duration", "1"], ["calibrate"], ["cleanup"]):
        result = runner.invoke(netem_app, argv)
        assert result.exit_code == 1, argv
        assert result.stdout == ""
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, lines
        assert "needs root" in lines[0]
        assert "Traceback" not in result.stderr


def test_invalid_option_is_a_usage_error(runner: CliRunner) -> None:
    result = runner.invoke(netem_app, ["shell", "--loss", "150"])
    assert result.exit_code == 2
    result = runner.invoke(netem_app, ["shell", "--duration", "100000"])
    assert result.exit_code == 2


@needs_emulator
def test_check_says_available(runner: CliRunner) -> None:
    result = runner.invoke(netem_app, ["check"])
    assert result.exit_code == 0
    assert "can run here" in result.stdout


@needs_emulator
def test_shell_brings_the_link_up_and_tears_it_down(runner: CliRunner) -> None:
    result = runner.invoke(
        netem_app,
        ["shell", "--delay", "7.5", "--loss", "1", "--direction", "a_to_b", "--duration", "0.3"],
    )
    assert result.exit_code == 0, result.stderr
    names = re.findall(r"namespace (rlb-\S+)", result.stdout)
    assert len(names) == 2
    assert f"ip netns exec {names[0]}" in result.stdout
    assert '"delay_ms":7.5' in result.stdout
    assert "duration elapsed; tearing down" in result.stdout
    assert not set(names) & set(list_namespaces())


@needs_emulator
def test_calibrate_reports_the_overhead(runner: CliRunner) -> None:
    result = runner.invoke(netem_app, ["calibrate", "--count", "50"])
    assert result.exit_code == 0, result.stderr
    assert "added by the relay (two hops, beyond 2 x delay): median" in result.stdout


@needs_emulator
def test_cleanup_runs(runner: CliRunner) -> None:
    result = runner.invoke(netem_app, ["cleanup"])
    assert result.exit_code == 0, result.stderr


@needs_emulator
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_shell_stops_cleanly_on_signal(sig: signal.Signals) -> None:
    src = str(Path(rlbridge.netem.__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from rlbridge.netem.cli import netem_app; "
            "netem_app(prog_name='rlbridge netem')",
            "shell",
            "--duration",
            "30",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        names = []
        for _ in range(20):  # bounded: the banner has fewer lines
            line = proc.stdout.readline()
            names += re.findall(r"namespace (rlb-\S+)", line)
            if line.startswith("run commands with"):
                break
        assert len(names) == 2
        assert set(names) <= set(list_namespaces())
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "tearing down" in out
    assert "Traceback" not in err
    assert not set(names) & set(list_namespaces())
