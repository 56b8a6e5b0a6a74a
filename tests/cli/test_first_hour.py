"""What a new user meets in the first hour (issue 27): each edge as a real process against a
real server on loopback, or (-h, help) on the real command tree."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import typer
from test_cli_e2e import assert_one_line_error

from rlbridge.cli.commands import build_app
from rlbridge.client.bridge import Bridge

F64 = "std_msgs/msg/Float64"
ROOT = Path(__file__).resolve().parents[2]


# -- YAML on the base install ---------------------------------------------------------------


def test_pyyaml_is_a_dependency_of_every_install_not_of_an_extra() -> None:
    """`service call ... '{data: true}'` (README) parses with PyYAML: the quick start's
    `pip install -e .` must bring it, so it is in [project] dependencies."""
    project = (ROOT / "pyproject.toml").read_text().split("[project]", 1)[1]
    dependencies = project.split("dependencies = [", 1)[1].split("]", 1)[0]
    assert re.search(r'^\s*"pyyaml>=6",', dependencies, re.M | re.I), dependencies


# -- topic pub ---------------------------------------------------------------------------------


def test_pub_count_without_rate_publishes_count(cli: Any, shared_cli_server: int) -> None:
    """Exit 0 means the server counted every one of the five (rlbridge.cli.delivery)."""
    result = cli.run("topic", "pub", "/first/count", F64, "1.5", "--count", "5", "-t", "tcp",
                     "-p", str(shared_cli_server))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "published 5 message(s) on /first/count"


@pytest.mark.parametrize(("command", "option"), [
    (("pub", "/first/rate", F64, "1.5"), ("--rate", "-5")),
    (("pub", "/first/rate", F64, "1.5"), ("--count", "0")),
    (("echo", "/first/rate", F64), ("--timeout", "-1")),
    (("echo", "/first/rate", F64), ("--count", "-1")),
    (("hz", "/first/rate", F64), ("--duration", "-1")),
    (("hz", "/first/rate", F64), ("--window", "1")),
])
def test_a_negative_rate_or_no_messages_is_a_usage_error(
        cli: Any, shared_cli_server: int, command: tuple[str, ...],
        option: tuple[str, str]) -> None:
    """Refused before anything connects (a negative --rate used to mean "once")."""
    result = cli.run("topic", *command, *option, "-p", str(shared_cli_server))
    assert result.returncode == 2, result
    assert f"Invalid value for '{option[0]}'" in result.stderr
    assert result.stdout == ""


def test_a_negative_value_needs_no_double_dash(
        cli: Any, shared_cli_server: int, bridge: Callable[..., Bridge]) -> None:
    reader = bridge(port=shared_cli_server)
    ch = reader.subscribe("/first/negative", F64, transport="tcp", blocking=True,
                          buffer_size=16)
    result = cli.run("topic", "pub", "/first/negative", F64, "-5", "-t", "tcp",
                     "-p", str(shared_cli_server))
    assert result.returncode == 0, result.stderr
    assert ch.read(timeout=20) == -5.0


@pytest.mark.parametrize(("topic", "msg_type", "value", "field", "says"), [
    ("bad name", F64, "1", "data", "is not a valid topic name"),
    ("/first/bad", F64, '"text"', "data", "needs a float"),
    ("/first/bad", "std_msgs/msg/Float65", "1", "data", "unknown message type"),
    ("/first/bad2", F64, "1", "dta", "dta"),
])
def test_what_the_command_line_got_wrong_exits_2(
        cli: Any, shared_cli_server: int, topic: str, msg_type: str, value: str, field: str,
        says: str) -> None:
    result = cli.run("topic", "pub", topic, msg_type, value, "-f", field, "-t", "tcp",
                     "-p", str(shared_cli_server))
    assert result.returncode == 2, result
    assert_one_line_error(result, says)


def test_over_the_rate_limit_pub_prints_only_its_one_error_line(
        cli: Any, cli_server: Callable[..., Any]) -> None:
    port, _server = cli_server("--max-rate", "5")
    result = cli.run("topic", "pub", "/first/limited", F64, "1.5", "--rate", "500", "--count",
                     "40", "-t", "udp", "-p", str(port))
    line = assert_one_line_error(result, "of 40 value(s) published on /first/limited")
    assert result.returncode == 1
    assert "--max-rate" in line


def test_empty_lists_say_so_on_stderr_and_exit_0(
        cli: Any, cli_server: Callable[..., Any]) -> None:
    port, _server = cli_server()
    for what in ("topic", "service"):
        result = cli.run(what, "list", "-p", str(port))
        assert result.returncode == 0, result.stderr
        assert result.stdout == ""
        assert result.stderr == f"no {what}s on this server yet\n"


# -- help: -h everywhere, the same text as docs/cli.md --------------------------------------


def _paths(group: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    yield path
    for name, sub in getattr(group, "commands", {}).items():
        if not sub.hidden:
            yield from _paths(sub, (*path, name))


def _sections() -> dict[str, str]:
    text = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    parts = re.split(r"^## (rlbridge.*)$", text, flags=re.MULTILINE)
    return {name: body.split("```text\n", 1)[1].rsplit("\n```", 1)[0]
            for name, body in zip(parts[1::2], parts[2::2], strict=True)}


def test_dash_h_prints_docs_cli_md_for_every_command() -> None:
    """One process walks the whole tree (a process per command would take a minute): each
    command's `-h` at 100 columns is its section of docs/cli.md, character for character."""
    paths = list(_paths(typer.main.get_command(build_app())))
    assert len(paths) > 30
    script = (
        "import contextlib, io, json, sys\n"
        "from rlbridge.cli.commands import build_app\n"
        "out = {}\n"
        f"for path in {[list(p) for p in paths]!r}:\n"
        "    buf = io.StringIO()\n"
        "    with contextlib.redirect_stdout(buf):\n"
        "        try:\n"
        "            build_app()([*path, '-h'], prog_name='rlbridge')\n"
        "        except SystemExit as exc:\n"
        "            assert exc.code in (0, None), (path, exc.code)\n"
        "    out[' '.join(['rlbridge', *path])] = buf.getvalue()\n"
        "print(json.dumps(out))\n")
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env=env, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    helps = json.loads(done.stdout)
    sections = _sections()
    assert set(helps) == set(sections)
    for name, text in helps.items():
        assert text.rstrip() == sections[name], name
        assert "-h, --help" in text, name


def test_help_has_no_markup_no_type_of_a_flag_and_upper_case_arguments() -> None:
    sections = _sections()
    for name, text in sections.items():
        assert "``" not in text, name  # no RST
        assert ":func:" not in text, name
        assert "<bool>" not in text, name
        usage = text.splitlines()[0]
        assert not re.search(r"[{\[][a-z]", usage.replace("[OPTIONS]", "")), usage
    assert "[default: warning; serve: info]" in sections["rlbridge"]


# -- --version on a pure wheel ---------------------------------------------------------------


def test_version_of_a_pure_wheel_does_not_advise_installing_it_again(tmp_path: Path) -> None:
    """The board's wheel (README): `pip install` of it compiles nothing, so "install again"
    cannot help; --version says what does."""
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "-w", str(tmp_path), "--no-deps",
         "-q"], capture_output=True, text=True, timeout=300, check=False,
        env={**os.environ, "RLBRIDGE_PURE_PYTHON": "1"})
    assert built.returncode == 0, built.stderr[-2000:]
    wheel = next(tmp_path.glob("rlbridge_sdk-*-py3-none-any.whl"))
    with zipfile.ZipFile(wheel) as z:
        assert not [n for n in z.namelist() if n.endswith(".so")]
    target = tmp_path / "site"
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target",
         str(target), str(wheel)], capture_output=True, text=True, timeout=300, check=False)
    assert installed.returncode == 0, installed.stderr[-2000:]
    version = subprocess.run(
        [sys.executable, "-m", "rlbridge", "--version"], capture_output=True, text=True,
        timeout=60, check=False, cwd=tmp_path,  # as a user runs it: no RLBRIDGE_PURE_PYTHON
        env={k: v for k, v in os.environ.items() if k != "RLBRIDGE_PURE_PYTHON"}
        | {"PYTHONPATH": str(target)})
    assert version.returncode == 0, version.stderr
    lines = version.stdout.splitlines()
    assert lines[1] == "value path: pure Python (not compiled for this interpreter)"
    assert lines[2] == ("sealing (ChaCha20-Poly1305): cryptography (the libsodium extension "
                        "was not built)")
    assert lines[3].startswith(f"to compile: this is a pure-Python wheel ({wheel.name}): "
                               "installing it again changes nothing; ")
    assert "pip install . from an rlbridge checkout on this machine" in lines[3]
