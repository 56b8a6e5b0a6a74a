"""rlbridge: a bridge between hard-real-time control code and ROS 2, over TCP and UDP.

Names (``from rlbridge import ...``):

    Bridge      the client SDK: ``Bridge.connect(host, port)``, then ``subscribe`` and
                ``publish`` return CSP channels bound to topics (``help(rlbridge.Bridge)``)
    LinkState   ``connected``, ``degraded`` or ``lost`` (``bridge.link_state``)
    __version__ the installed version

The server is the command ``rlbridge serve`` (or :class:`rlbridge.server.Server`);
``rlbridge --help`` or ``python -m rlbridge --help`` lists every command. The distribution
is ``rlbridge-sdk`` (``pip install -e .`` from a checkout). Importing this package imports
neither asyncio's server machinery nor rclpy: the names above load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rlbridge import _compiled  # noqa: F401  (first: it decides how the compiled modules load)
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


def __dir__() -> list[str]:
    """The lazy names too, so ``dir(rlbridge)`` and completion show ``Bridge``."""
    return sorted({*globals(), *__all__})
