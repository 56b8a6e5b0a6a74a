"""The two ways a client session fails, shared by the connection and its handshake.

They live apart from :mod:`rlbridge.csp.connection` (which re-exports them, the public place
to import them from) so the handshake and the receive thread can raise them without
importing the connection itself.
"""

from __future__ import annotations

from rlbridge.wire import RlbridgeError


class ConnectionFailed(RlbridgeError):
    """The bridge server could not be reached or refused the session."""


class ConnectionClosed(RlbridgeError):
    """The connection was closed (by this program, the server, or the watchdog)."""
