"""``rlbridge demo``: a server, a publisher and a subscriber in one command."""

from __future__ import annotations

import math
import time
from typing import Annotated

import typer


def register_demo(app: typer.Typer) -> None:
    """Add the ``demo`` command to the main app."""

    @app.command()
    def demo(
        seconds: Annotated[float, typer.Option(help="How long to run.")] = 5.0,
        rate: Annotated[float, typer.Option(help="Set-point rate (Hz).")] = 100.0,
    ) -> None:
        """Start a bridge server and two clients; watch a set-point stream cross it over UDP."""
        from rlbridge.csp.bridge import Bridge
        from rlbridge.server import ServerThread

        with ServerThread() as server:
            typer.echo(f"bridge server on 127.0.0.1:{server.port} (in-process bus)")
            with Bridge.connect("127.0.0.1", server.port, name="demo-controller") as ctl, \
                    Bridge.connect("127.0.0.1", server.port, name="demo-vision") as vision:
                setpoint_in = ctl.subscribe("/demo/setpoint", "std_msgs/msg/Float64",
                                            transport="udp", initial=0.0)
                status_in = ctl.subscribe("/demo/status", "std_msgs/msg/String",
                                          transport="tcp", blocking=True, buffer_size=16)
                setpoint_out = vision.publish("/demo/setpoint", "std_msgs/msg/Float64",
                                              transport="udp")
                status_out = vision.publish("/demo/status", "std_msgs/msg/String",
                                            transport="tcp")
                status_out.write("tracking")
                typer.echo(f"status over TCP: {status_in.read(timeout=5.0)!r}")
                period = 1.0 / rate
                start = time.monotonic()
                n = int(seconds * rate)
                for i in range(n):
                    setpoint_out.write(math.sin(2 * math.pi * 0.5 * i * period))
                    time.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))
                    if i % int(rate / 2 or 1) == 0:
                        value = setpoint_in.read()
                        typer.echo(f"t={i * period:5.2f}s  set-point read by controller: "
                                   f"{value:+.3f}  (age {setpoint_in.age_ns / 1e6:.2f} ms, "
                                   f"link {ctl.link_state.value})")
                time.sleep(0.05)
                stats = setpoint_in.statistics()
                typer.echo(f"sent {n} set-points at {rate:g} Hz over UDP; controller channel: "
                           f"{stats.written} arrived, {setpoint_in.lost} lost")
