"""Authorization: which topics a client may publish and subscribe to, and whose Stats it sees.

Rules come from the key file (:mod:`rlbridge.keyfile`), per *identity*: the common name of a
client's mutual-TLS certificate, or the client name whose own key it proved. A client with no
proven name (the default key, TLS without a client certificate) gets the default (``*``) line's
rules. A server without rules allows every topic. Stats: on a server that authenticates
clients (keys or mutual TLS) a client sees only its own session unless its line says
``stats=all``; on an open server nobody is told apart, so everybody sees all.
"""

from __future__ import annotations

from rlbridge.keyfile import DEFAULT, Entry


class Access:
    """The rules of one server run."""

    def __init__(self, entries: dict[str, Entry] | None = None, *,
                 authenticated: bool = False) -> None:
        self._entries = dict(entries or {})
        self.authenticated = authenticated

    def rules(self, identity: str | None) -> Entry | None:
        """The line that applies to ``identity``: its own, else the default one, else None."""
        own = self._entries.get(identity) if identity is not None else None
        return own or self._entries.get(DEFAULT)

    def refusal(self, identity: str | None, direction: str, topic: str) -> str | None:
        """Why ``identity`` may not ``direction`` ``topic`` (a sentence), or None if it may."""
        rules = self.rules(identity)
        if rules is None or rules.allows(direction, topic):
            return None
        who = f"client {identity!r}" if identity is not None else "a client without a proven name"
        verb = "publish to" if direction == "publish" else "subscribe to"
        return (f"{who} may not {verb} {topic}: not in its allowed {direction} topics "
                f"({rules.globs(direction)}) in the server's key file")

    def sees_all(self, identity: str | None) -> bool:
        """True if ``identity`` may see every session's counters in Stats."""
        if not self.authenticated:
            return True
        rules = self.rules(identity)
        return rules is not None and rules.see_all
