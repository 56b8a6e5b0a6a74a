"""The ``rlbridge`` command: typer commands that build the same option objects the API takes, and
call the library."""

from rlbridge.cli.commands import main

__all__ = ["main"]
