"""``rlbridge demo``: the thesis's pan-tilt camera (section 3.1), simulated, over a real bridge.

The command only turns options into a :class:`~rlbridge.demo.run.DemoOptions` and calls
:func:`~rlbridge.demo.run.run_demo`; the library does the rest.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated, Literal

import typer

from rlbridge.cli.errors import fail, one_line_errors
from rlbridge.cli.options import PskFileOpt, option, psk_of
from rlbridge.demo.plot import DEFAULT_NAME, resolve_path

ROLES = ("all", "bridge", "controller")
DEFAULT_PORT = 7411
#: The key file a bridge on an address other than loopback makes and uses by default.
DEMO_KEY = "rlbridge-demo.key"


def register_demo(app: typer.Typer) -> None:
    """Add the ``demo`` command to the main app."""

    @app.command()
    @one_line_errors
    def demo(
        seconds: Annotated[float | None, typer.Option(
            help="How long to run; 0: until Ctrl-C / SIGTERM (all: 5; bridge, controller: 0).",
            show_default=False)] = None,
        role: Annotated[str, typer.Option(
            help="all: both sides in one process; bridge: server + vision node (middleware "
                 "side); controller: the embedded loop controller.")] = "all",
        host: Annotated[str, option(
            "--host", "bridge/all: address to bind; controller: server to reach.")]
        = "127.0.0.1",
        port: Annotated[int | None, option(
            "--port", f"Server port (all: any free port; else {DEFAULT_PORT}).")]
        = None,
        adapter: Annotated[str, typer.Option(
            help="Middleware of the bridge side: inproc or ros2.")] = "inproc",
        dashboard: Annotated[bool, typer.Option(
            "--dashboard/--no-dashboard",
            help="Live terminal view (only on a terminal; else one line a second).")] = True,
        plot: Annotated[str | None, typer.Option(
            help="PNG of set-points, angles and tracking error; a directory (out/, or a name "
                 f"without an extension) gets DIR/{DEFAULT_NAME}, created if missing "
                 f"[default: ./{DEFAULT_NAME}].", show_default=False)]
        = None,
        no_plot: Annotated[bool, typer.Option("--no-plot", help="Do not write the plot.")]
        = False,
        report: Annotated[Path | None, typer.Option(
            help="Write the results as JSON to this file.")] = None,
        dropout_at: Annotated[float, typer.Option(
            help="The vision node loses the target at this time (s) ...")] = 2.0,
        dropout_for: Annotated[float, typer.Option(
            help="... for this long (s; 0: never), so the controller holds position.")] = 0.5,
        namespace: Annotated[str, typer.Option(help="Topic namespace.")] = "/pan_tilt",
        connect_timeout: Annotated[float, typer.Option(
            help="controller: keep trying to reach the server this long (s).")] = 30.0,
        psk_file: PskFileOpt = None,
        lost_exit: Annotated[float, typer.Option(
            help="controller: exit with status 3 after the link was lost this long (s); "
                 "0: never, reconnect and resume.")]
        = 0.0,
    ) -> None:
        """Pan-tilt camera demo: a 1 kHz loop controller tracks a 30 Hz vision node's set-points.

        The controller reads set-points from non-blocking UDP channels, sends its angles back
        sub-sampled to 50 Hz and its state (idle, tracking, safe, lost-link) over TCP. The
        vision node follows a target on a Lissajous path, losing it for a moment halfway.

        --psk-file: the bridge side (all, bridge) makes the file (a new random key, mode 600)
        if it is missing and serves with it; the controller connects with it. A bridge on an
        address other than loopback without $RLBRIDGE_PSK uses ./rlbridge-demo.key.
        """
        from rlbridge.demo.plot import PlotUnavailable
        from rlbridge.demo.run import DemoOptions, run_demo
        from rlbridge.demo.vision import Dropout
        from rlbridge.server.config import is_loopback
        from rlbridge.wire.auth import PSK_ENV

        if role not in ROLES:
            raise fail(f"--role must be one of {', '.join(ROLES)}, not '{role}'", 2)
        if adapter not in ("inproc", "ros2"):
            raise fail(f"--adapter must be inproc or ros2, not '{adapter}'", 2)
        if seconds is None:
            seconds = 5.0 if role == "all" else 0.0
        if seconds < 0:
            raise fail("--seconds must be >= 0", 2)
        if (psk_file is None and role != "controller" and not is_loopback(host)
                and not os.environ.get(PSK_ENV)):
            psk_file = DEMO_KEY  # secure by default: a bridge others can reach has a key
        chosen: Literal["all", "bridge", "controller"] = role  # type: ignore[assignment]
        middleware: Literal["inproc", "ros2"] = adapter  # type: ignore[assignment]
        options = DemoOptions(
            role=chosen,
            seconds=seconds,
            host=host,
            port=port if port is not None else (0 if role == "all" else DEFAULT_PORT),
            adapter=middleware,
            namespace=namespace,
            dropout=Dropout(dropout_at, dropout_for),
            dashboard=dashboard and sys.stdout.isatty(),
            plot=None if no_plot or role == "controller" else resolve_path(plot or DEFAULT_NAME),
            plot_required=plot is not None,
            report=report,
            connect_timeout=connect_timeout,
            lost_exit=lost_exit,
            psk=psk_of(psk_file),
        )
        try:
            result = run_demo(options, sys.stdout)
        except PlotUnavailable as exc:
            raise fail(str(exc)) from None
        if result.exit_code:
            raise typer.Exit(result.exit_code)
