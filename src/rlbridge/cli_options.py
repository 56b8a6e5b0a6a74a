"""The options several ``rlbridge`` commands share, defined once so they mean one thing.

:data:`SHORT_OPTIONS` is the only place a short option is given out: ``-H`` is ``--host`` in
every command that has a host (``serve`` and ``demo`` included), ``-t`` is ``--transport``
wherever there is a transport, and no command gives either letter another meaning
(``tests/cli/test_options.py`` walks every command to check). :func:`option` builds a
``typer.Option`` with the long name, its short one if it has one, and the help text.
"""

from __future__ import annotations

import logging
import re
import sys
from typing import TYPE_CHECKING, Any

import typer

from rlbridge.cli_errors import fail

if TYPE_CHECKING:
    from pydantic import ValidationError

#: Long option -> its one short form, for every command.
SHORT_OPTIONS: dict[str, str] = {
    "--host": "-H",
    "--port": "-p",
    "--field": "-f",
    "--transport": "-t",
}

LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"


def option(long: str, help: str, **kwargs: Any) -> Any:
    """``typer.Option(long, SHORT_OPTIONS[long], help=...)``; the short one only if it has one."""
    short = SHORT_OPTIONS.get(long)
    return typer.Option(long, *([short] if short else []), help=help, **kwargs)


def check_log_level(value: str | None) -> str | None:
    """A typer callback: one of :data:`LOG_LEVELS` (any case), else one error line, exit 2."""
    if value is None:
        return None
    if value.lower() not in LOG_LEVELS:
        raise fail(f"--log-level must be one of {', '.join(LOG_LEVELS)}, not '{value}'", 2)
    return value.lower()


def check_transport(value: str) -> str:
    """A typer callback: ``udp`` or ``tcp``, checked before the command connects anywhere."""
    if value not in ("udp", "tcp"):
        raise fail(f"--transport must be 'udp' or 'tcp', not '{value}'", 2)
    return value


def configure_logging(level: str) -> None:
    """Log to stderr at ``level``; called again by ``serve`` with its own level (force)."""
    logging.basicConfig(level=level.upper(), stream=sys.stderr, format=LOG_FORMAT, force=True)


LOG_LEVEL_HELP = f"{', '.join(LOG_LEVELS)}."


def config_error(exc: ValidationError) -> str:
    """A config validation error in the command line's words: ``--timeout-ms``, not the
    config field ``timeout_ms`` (the message names the options a user typed)."""
    first = exc.errors()[0]
    fields = [str(p) for p in first["loc"]]
    message = str(first["msg"]).removeprefix("Value error, ")
    message = re.sub(r"\b([a-z]+(?:_[a-z]+)+)\b",
                     lambda m: "--" + m.group(1).replace("_", "-"), message)
    where = ", ".join("--" + f.replace("_", "-") for f in fields)
    return f"{where}: {message}" if where else message
