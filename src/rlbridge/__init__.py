"""rlbridge: a bridge between hard-real-time control code and ROS 2, over TCP and UDP.

The client SDK is ``from rlbridge import Bridge``; the server is ``rlbridge serve`` (or
:class:`rlbridge.server.Server`). Importing this package imports neither asyncio's server
machinery nor rclpy: the names below load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rlbridge._version import __version__

if TYPE_CHECKING:
    from rlbridge.csp.bridge import Bridge
    from rlbridge.wire.link import LinkState

__all__ = ["Bridge", "LinkState", "__version__"]


def __getattr__(name: str) -> Any:
    if name == "Bridge":
        from rlbridge.csp.bridge import Bridge

        return Bridge
    if name == "LinkState":
        from rlbridge.wire.link import LinkState

        return LinkState
    raise AttributeError(f"module 'rlbridge' has no attribute {name!r}")
