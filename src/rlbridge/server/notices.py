"""What the server tells its operator: one line when it listens, one when it stops, and what
clients got wrong, at most once per kind and interval.

A server that says nothing leaves the operator guessing whether it runs, where, and why a
client cannot get in. A server that logs every refused datagram lets one broken (or hostile)
client fill the disk. :class:`Notices` is the middle: the first occurrence of each kind of
problem is logged with its reason at WARNING; later ones within ``interval_s`` are counted,
and the next line that gets through says how many were not shown.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import time
from collections.abc import Callable

#: Seconds between two warnings of the same kind.
NOTICE_INTERVAL_S = 10.0
#: The client name of ``rlbridge ping``: a health probe without a key, refused by a server
#: that requires one, is not worth a warning every few seconds.
PROBE_NAME = "rlbridge-ping"


class Notices:
    """Rate-limited warnings, per kind (``"auth"``, ``"malformed"``, ``"refused channel"``)."""

    def __init__(self, logger: logging.Logger, interval_s: float = NOTICE_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = logger
        self._interval = interval_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warn(self, kind: str, message: str) -> bool:
        """Log ``message`` unless ``kind`` was logged less than the interval ago (then count
        it); True if it was logged."""
        now = self._clock()
        last = self._last.get(kind)
        if last is not None and now - last < self._interval:
            self._held[kind] = self._held.get(kind, 0) + 1
            return False
        self._last[kind] = now
        held = self._held.pop(kind, 0)
        more = (f" ({held} more {kind} notice(s) in the last {self._interval:g} s not shown)"
                if held else "")
        self._log.warning("%s%s", message, more)
        return True


def peer_address(peer: object) -> str:
    """``host:port`` (``[v6]:port``) of a socket address, for the operator's log lines."""
    if isinstance(peer, tuple) and len(peer) >= 2:
        host = str(peer[0])
        return f"[{host}]:{peer[1]}" if ":" in host else f"{host}:{peer[1]}"
    return "?" if peer is None else str(peer)


def session_level(name: str) -> int:
    """INFO for a session's opening and closing; DEBUG for a health probe's (every few s)."""
    return logging.DEBUG if name == PROBE_NAME else logging.INFO


def listening_line(host: str, port: int, tcp: bool, udp: bool, adapter: str,
                   authentication: str, metrics_port: int | None,
                   metrics_host: str = "127.0.0.1") -> str:
    """``listening on 127.0.0.1 port 7411 (TCP and UDP), adapter inproc, authentication ...``."""
    transports = " and ".join(name for name, on in (("TCP", tcp), ("UDP", udp)) if on)
    where = f"[{metrics_host}]" if ":" in metrics_host else metrics_host
    metrics = f", metrics on http://{where}:{metrics_port}/metrics" if metrics_port else ""
    return (f"rlbridge listening on {host} port {port} ({transports}), adapter {adapter}, "
            f"authentication: {authentication}{metrics}")


def bind_failure(transport: str, host: str, port: int, exc: OSError,
                 option: str = "--port") -> str:
    """Why the server cannot listen, for people: which transport (``TCP``, ``UDP``, or
    ``metrics``), which port, what to do (``option`` is the port's option)."""
    if exc.errno is None and isinstance(exc.__cause__, OSError):
        exc = exc.__cause__  # uvloop: "could not bind to local_addr", the errno is its cause
    head = (f"cannot serve metrics on {host} port {port}" if transport == "metrics"
            else f"cannot listen on {host} {transport} port {port}")
    if isinstance(exc, socket.gaierror):  # a name that does not resolve: errno is EAI_*
        return f"{head}: {exc.strerror or exc}; see --host"
    reason = os.strerror(exc.errno) if exc.errno else str(exc)
    advice = {
        errno.EADDRINUSE: "another program (or another rlbridge serve) has it: stop it, or "
                          f"choose another {option} (0: any free port)",
        errno.EACCES: f"ports below 1024 need root: choose a {option} above 1023",
        errno.EADDRNOTAVAIL: f"{host} is not an address of this machine: see --host",
    }.get(exc.errno or 0)
    return f"{head}: {reason.lower()}" + (f"; {advice}" if advice else "")
