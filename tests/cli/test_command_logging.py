"""A command run in-process logs to its stderr while it runs and leaves logging as it found it.

``configure_logging`` used ``logging.basicConfig(stream=sys.stderr, force=True)``: run through
typer's ``CliRunner`` (as tests do), the root logger kept a handler bound to the runner's
stderr, which the runner closes, and every later log line of the test process (a
``ServerThread``'s "session closed") was a ``--- Logging error ---`` traceback; ``force`` also
took pytest's own handlers off the root logger.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import pytest
from typer.testing import CliRunner

from log_handlers import on_closed_streams
from rlbridge.cli.commands import build_app
from rlbridge.server import ServerThread


def test_serve_leaves_the_root_logger_as_it_found_it(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    # Both the group's and serve's own set-up run before the config is refused (exit 2).
    result = CliRunner().invoke(build_app(), ["--log-level", "debug", "serve",
                                              "--log-level", "info",
                                              "--udp-receive-buffer", "1024"])
    assert result.exit_code == 2, result.output
    assert on_closed_streams() == []
    assert root.handlers == handlers
    assert root.level == level
    logging.getLogger("rlbridge.server").warning("after the command")
    assert "Logging error" not in capsys.readouterr().err


def test_a_command_logs_to_its_stderr_at_its_level_while_it_runs(
        make_server: Callable[..., ServerThread]) -> None:
    srv = make_server()
    argv = ["topic", "list", "--port", str(srv.port)]
    quiet = CliRunner().invoke(build_app(), argv)
    loud = CliRunner().invoke(build_app(), ["--log-level", "info", *argv])
    assert quiet.exit_code == loud.exit_code == 0, (quiet.output, loud.output)
    said = "rlbridge.client INFO session ended (closed): closed by the client"
    assert said not in quiet.stderr
    assert loud.stderr.count(said) == 1, loud.stderr
