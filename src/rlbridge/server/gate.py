"""The door every client passes, over TCP or UDP: network allow-list, then key, then session.

Without keys a hello opens a session at once (the registry checks version and limits). With
keys the hello gets an :class:`~rlbridge.wire.AuthChallenge` and only a correct
:class:`~rlbridge.wire.AuthProof` opens the session, whose datagrams are then sealed with the
derived keys (:mod:`rlbridge.wire.auth`). Every refusal is counted in the server's counters
(``auth_failed``, ``not_allowed``) and answered with a ``ConnectError`` that says why.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

from rlbridge.server.notices import PROBE_NAME
from rlbridge.server.registry import SessionRegistry
from rlbridge.server.session import Session
from rlbridge.wire import (
    AuthProof,
    ConnectError,
    Disconnect,
    ErrorCode,
    Hello,
    RemoteProtocolError,
)
from rlbridge.wire.auth import NONCE_SIZE, ServerHandshake, sealed_codec

log = logging.getLogger("rlbridge.server")

Outcome = Session | ConnectError | ServerHandshake


class Gate:
    """Stateless rules; the transport keeps a pending :class:`ServerHandshake` between steps."""

    def __init__(self, registry: SessionRegistry,
                 random: Callable[[int], bytes] = os.urandom) -> None:
        self._registry = registry
        self._random = random

    def allowed(self, host: str, what: str) -> ConnectError | None:
        """None if ``host`` may connect, else the refusal (counted)."""
        ctx = self._registry.ctx
        if ctx.allow.allows(host):
            return None
        ctx.count("not_allowed")
        ctx.notices.warn("allow-list", f"refused {what} from {host}: not in the allow-list")
        return ConnectError(int(ErrorCode.NOT_ALLOWED),
                            f"client address {host} is not in this server's allow-list")

    def hello(self, hello: Hello, peer: str, *, udp: bool = False) -> Outcome:
        """A session, a refusal, or (keys configured) the handshake to send a challenge for.

        A server whose only protection is TLS refuses UDP hellos: a session opened over UDP
        would have no keys at all (a TCP session's datagrams get theirs over TLS). ``peer``
        (``host:port``) is for the warnings: the operator needs to know which machine it was.
        """
        ctx = self._registry.ctx
        keys = ctx.keys
        if keys is None and udp and ctx.tls is not None:
            ctx.count("udp_hello_refused")
            return ConnectError(int(ErrorCode.AUTH_FAILED), "this server protects sessions "
                                "with TLS: open the session over TCP with TLS (its UDP "
                                "channels get their keys over it)")
        if keys is None:
            return self._registry.open(hello)
        key = keys.key_for(hello.name)
        if key is None:
            return self._refuse(f"no pre-shared key for client name {hello.name!r}", hello,
                                peer)
        try:
            return ServerHandshake(key, hello.name, hello.auth, self._random(NONCE_SIZE))
        except RemoteProtocolError as exc:
            return self._refuse(exc.reason, hello, peer)

    def finish(self, handshake: ServerHandshake, hello: Hello, proof: AuthProof, peer: str
               ) -> Session | ConnectError:
        """Check the client's proof; open its session with sealed datagrams if right."""
        try:
            keys = handshake.verify(proof)
        except RemoteProtocolError as exc:
            return self._refuse(exc.reason, hello, peer)
        result = self._registry.open(hello)
        if isinstance(result, Session):
            result.codec = sealed_codec(keys, server=True)
            result.keys = keys
            store = self._registry.ctx.keys
            result.identity = store.identity(hello.name) if store is not None else None
            self._registry.ctx.count("sessions_authenticated")
        return result

    def abandoned(self, goodbye: Disconnect, hello: Hello, peer: str) -> None:
        """The client hung up during the handshake; with AUTH_FAILED it refused our proof
        (its key is not this server's key for its name)."""
        if goodbye.code == ErrorCode.AUTH_FAILED:
            self._registry.ctx.count("auth_failed")
            self._registry.ctx.notices.warn(
                "authentication", f"authentication failed for client {hello.name!r} from "
                f"{peer}: {goodbye.reason.removeprefix('authentication failed: ')}")

    def _refuse(self, reason: str, hello: Hello, peer: str) -> ConnectError:
        self._registry.ctx.count("auth_failed")
        if hello.name == PROBE_NAME and not hello.auth:
            return ConnectError(int(ErrorCode.AUTH_FAILED), reason)  # a health probe
        self._registry.ctx.notices.warn(
            "authentication", f"authentication failed for client {hello.name!r} from {peer}: "
            f"{reason.removeprefix('authentication failed: ')}")
        return ConnectError(int(ErrorCode.AUTH_FAILED), reason)
