"""The two sides of the bridge as context managers: what each starts, and in which order it stops.

* :func:`middleware_side`: the resource-rich machine. A middleware adapter (the in-process bus,
  or ROS 2), a bridge server on it, and the vision and monitor nodes on the same middleware.
  The server tells the trace when the controller's session closes: the controller cannot
  report its own absence, and its last report would otherwise stand for it.
* :func:`connect_controller`: the embedded board's session with the server, retried until the
  server answers (in docker compose the controller may start first).

Every thread these start is stopped and joined on the way out, innermost first: the vision
node's frame thread, the monitor's subscriptions, the server thread, then the adapter.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rlbridge import AuthenticationFailed, Bridge, ConnectionFailed, Psk
from rlbridge.adapters import MiddlewareAdapter, load_adapter
from rlbridge.demo.monitor import Monitor, Trace
from rlbridge.demo.topics import Topics
from rlbridge.demo.vision import Dropout, VisionNode
from rlbridge.server import ServerConfig, ServerThread

AdapterName = Literal["inproc", "ros2"]
#: The name the controller's session has on the server (``Hello.name``): how the bridge side
#: tells the controller's session from any other client's.
CONTROLLER_NAME = "pan-tilt-controller"


@dataclass(frozen=True)
class MiddlewareSide:
    """What :func:`middleware_side` yields."""

    server: ServerThread
    adapter: MiddlewareAdapter
    trace: Trace
    vision: VisionNode
    monitor: Monitor

    @property
    def port(self) -> int:
        return self.server.port


@contextmanager
def middleware_side(*, host: str = "127.0.0.1", port: int = 0, adapter: AdapterName = "inproc",
                    topics: Topics | None = None, vision_start: float = 0.5,
                    dropout: Dropout | None = None,
                    psk_file: Path | None = None) -> Iterator[MiddlewareSide]:
    """Start the adapter, the server on it, and the vision and monitor nodes; stop them after.

    The server gets ``nodelay=True``: the status and diagnostics it forwards over TCP are small
    and sporadic, exactly the packets Nagle's algorithm would hold back (thesis 3.3.2).
    """
    with ExitStack() as stack:
        mw = load_adapter(adapter, node_name="rlbridge_pan_tilt")
        stack.callback(mw.close)
        config = ServerConfig(host=host, port=port, adapter=adapter, nodelay=True,
                              psk_file=psk_file)
        server = stack.enter_context(ServerThread(config, adapter=mw))
        trace = Trace()
        registry = server.server.registry
        assert registry is not None  # the thread has started
        registry.on_forget.append(
            lambda session: trace.controller_left() if session.name == CONTROLLER_NAME else None)
        monitor = Monitor(mw, trace, topics=topics)
        stack.callback(monitor.close)
        vision = VisionNode(mw, trace, topics=topics, start_after=vision_start, dropout=dropout)
        stack.callback(vision.close)
        vision.start()
        yield MiddlewareSide(server, mw, trace, vision, monitor)


def connect_controller(host: str, port: int, *, timeout: float = 30.0,
                       stop: threading.Event | None = None,
                       name: str = CONTROLLER_NAME,
                       security: Psk | None = None) -> Bridge:
    """``Bridge.connect`` again and again (backing off to 1 s) until it works or ``timeout``.

    Raises :class:`~rlbridge.ConnectionFailed` with the last reason when the time is up or
    ``stop`` is set. ``security``: the key (``rlbridge demo --psk-file`` builds it in the CLI's
    one place); a key file that does not exist yet (the bridge side makes it when it starts)
    is waited for like a server that does not answer yet.
    """
    deadline = time.monotonic() + timeout
    delay = 0.1
    while True:
        remaining = deadline - time.monotonic()
        try:
            if security is not None and security.file is not None \
                    and not Path(security.file).exists():
                raise ConnectionFailed(f"no key file {security.file} yet")
            return Bridge.connect(host, port, nodelay=True, name=name, security=security,
                                  timeout=min(2.0, max(0.2, remaining)))
        except AuthenticationFailed:
            raise  # a wrong key or certificate: trying again will not help
        except ConnectionFailed as exc:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ConnectionFailed(f"{exc} (tried for {timeout:g} s)") from None
            if stop is not None and stop.wait(min(delay, remaining)):
                raise ConnectionFailed(f"{exc} (stopped while retrying)") from None
            if stop is None:
                time.sleep(min(delay, remaining))
            delay = min(2 * delay, 1.0)


@contextmanager
def switch_interval(seconds: float) -> Iterator[None]:
    """Shorten the GIL switch interval for a block (restored after).

    A thread that wakes up waits for the GIL up to one switch interval (5 ms by default, see
    :mod:`rlbridge.csp.timer`). The demo is the application, so it may choose 0.5 ms to keep
    the 1 kHz loop's lateness below a period while other Python threads run.
    """
    previous = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(previous)
