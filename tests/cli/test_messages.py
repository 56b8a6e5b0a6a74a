"""Messages for people: what went wrong in the user's words, checked before any I/O, naming
the file or option concerned, without protocol internals or SDK parameter names."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import typer

from rlbridge.cli_errors import one_line_errors
from rlbridge.csp.channel import Channel
from rlbridge.errors import NoValueYet


def test_a_bad_transport_is_refused_before_connecting(
        cli: Any, free_port: Callable[[], int]) -> None:
    result = cli.run("topic", "pub", "/x", "std_msgs/msg/Float64", "1", "-t", "tcpx",
                     "-p", str(free_port()))  # nothing listens there: no attempt is made
    assert result.returncode == 2
    assert result.stderr == "rlbridge: error: --transport must be 'udp' or 'tcp', not 'tcpx'\n"


def test_a_file_error_names_the_file(tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "no" / "such.json"

    @one_line_errors
    def write_report() -> None:
        missing.write_text("{}")

    with pytest.raises(typer.Exit) as exit_info:
        write_report()
    assert exit_info.value.exit_code == 1
    assert capsys.readouterr().err == (f"rlbridge: error: {missing}: No such file or "
                                       "directory\n")


def test_no_value_yet_says_where_to_give_an_initial_value() -> None:
    ch: Channel[float] = Channel(buffer_size=1, blocking=False, name="/camera/setpoint")
    with pytest.raises(NoValueYet) as info:
        ch.read()
    assert "bridge.subscribe(..., initial=0.0)" in str(info.value)
    assert "/camera/setpoint" in str(info.value)
