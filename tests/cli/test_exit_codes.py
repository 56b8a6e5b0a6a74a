"""Exit codes tell the truth: 0 only when the command did what was asked (real processes).

0: done; 1: could not (the server refused, nothing arrived, cannot reach it); 2: the command
line is wrong; 130: interrupted. Every failure is one ``rlbridge: error:`` line, no traceback.
"""

from __future__ import annotations

import signal
import subprocess
from collections.abc import Callable
from typing import Any

import pytest

F64 = "std_msgs/msg/Float64"
PROC_WAIT = 30.0


def last_error_line(result: subprocess.CompletedProcess[str], code: int = 1) -> str:
    """Exit ``code``, no traceback, and the last stderr line is the CLI's one error line.

    (Lines before it may be the SDK's own warnings, e.g. the server's reason for a refusal.)
    """
    assert result.returncode == code, (result.returncode, result.stdout, result.stderr)
    assert "Traceback" not in result.stderr, result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("rlbridge: error: "), result.stderr
    return line


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_pub_of_a_value_the_server_refuses_exits_non_zero(
        cli: Any, shared_cli_server: int, transport: str) -> None:
    result = cli.run("topic", "pub", f"/exit/bad/{transport}", F64, '"abc"', "-t", transport,
                     "-p", str(shared_cli_server))
    assert result.returncode != 0, result
    assert "published" not in result.stdout
    assert "Traceback" not in result.stderr
    assert "rlbridge: error: " in result.stderr.strip().splitlines()[-1]


def test_pub_over_the_servers_rate_limit_says_how_many_arrived(
        cli: Any, cli_server: Callable[..., Any]) -> None:
    port, _server = cli_server("--max-rate", "5")
    result = cli.run("topic", "pub", "/exit/limited", F64, "1.5", "--rate", "500", "--count", "40",
                     "-t", "tcp", "-p", str(port))
    line = last_error_line(result)
    assert "the server took 5 of 40 value(s) published on /exit/limited" in line, line
    assert "--max-rate" in line


def test_pub_of_a_value_the_server_takes_exits_0(cli: Any, shared_cli_server: int) -> None:
    for transport in ("udp", "tcp"):
        result = cli.run("topic", "pub", "/exit/good", F64, "2.5", "--rate", "200", "--count", "5",
                         "-t", transport, "-p", str(shared_cli_server))
        assert result.returncode == 0, result.stderr
        assert result.stdout.strip() == "published 5 message(s) on /exit/good"


def test_hz_that_hears_nothing_exits_1(cli: Any, shared_cli_server: int) -> None:
    result = cli.run("topic", "hz", "/exit/silent", F64, "--duration", "0.5",
                     "-p", str(shared_cli_server))
    assert "no value on /exit/silent within 0.5 s" in last_error_line(result)


def test_echo_that_hears_nothing_exits_1(cli: Any, shared_cli_server: int) -> None:
    result = cli.run("topic", "echo", "/exit/silent", F64, "--timeout", "0.5",
                     "-p", str(shared_cli_server))
    assert "no value on /exit/silent within 0.5 s" in last_error_line(result)


@pytest.mark.parametrize("args", [("--log-level", "loud", "topic", "list"),
                                  ("serve", "--log-level", "loud")])
def test_an_unknown_log_level_is_one_line_and_exit_2(cli: Any, args: tuple[str, ...]) -> None:
    result = cli.run(*args)
    line = last_error_line(result, 2)
    assert result.stderr.count("\n") == 1
    assert line == ("rlbridge: error: --log-level must be one of debug, info, warning, error, "
                    "not 'loud'")


def test_a_bad_server_option_names_the_option_not_the_config_field(
        cli: Any, free_port: Callable[[], int]) -> None:
    result = cli.run("serve", "--heartbeat-ms", "500", "--timeout-ms", "400",
                     "-p", str(free_port()))
    assert last_error_line(result, 2) == ("rlbridge: error: --timeout-ms must be longer than "
                                          "--heartbeat-ms")


def test_ctrl_c_on_a_client_tool_exits_130(
        cli: Any, shared_cli_server: int, topics_of: Callable[[int], Any],
        wait_until: Callable[..., Any]) -> None:
    echo = cli.popen("topic", "echo", "/exit/interrupted", F64, "-p", str(shared_cli_server))
    wait_until(lambda: "/exit/interrupted" in topics_of(shared_cli_server))
    echo.send_signal(signal.SIGINT)
    _out, err = echo.communicate(timeout=PROC_WAIT)
    assert echo.returncode == 130, err
    assert err == ""
