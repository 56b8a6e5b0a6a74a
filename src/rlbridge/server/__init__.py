"""The bridge server: asyncio, listeners, sessions; the only asyncio code in rlbridge."""

from rlbridge.server.app import BoundAddress, Server, ServerError, ServerThread, new_event_loop
from rlbridge.server.config import ServerConfig

__all__ = ["BoundAddress", "Server", "ServerConfig", "ServerError", "ServerThread",
           "new_event_loop"]
