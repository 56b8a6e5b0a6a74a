"""``rlbridge bench ...``: thin typer commands over the benchmark modules."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

bench_app = typer.Typer(help="Measure rlbridge next to a baseline from the same run.",
                        no_args_is_help=True)

Out = Annotated[Path, typer.Option("--out", help="Markdown file the figures are written to.")]
