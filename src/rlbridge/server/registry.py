"""Sessions by id and by UDP token; the gate every hello passes, whatever its transport."""

from __future__ import annotations

import secrets
from collections.abc import Callable, Iterator
from typing import Any

from rlbridge.server.context import ServerContext
from rlbridge.server.ledger import LiveLabels, channel_key
from rlbridge.server.session import Session
from rlbridge.server.session_stats import CHANNEL_TOTALS
from rlbridge.wire import PROTOCOL_VERSION, ConnectAck, ConnectError, ErrorCode, Hello, Limits

#: Per-session counters the server also reports summed over all sessions, closed ones too.
SESSION_TOTALS = ("packets_in", "bytes_in", "bytes_out",
                  *CHANNEL_TOTALS)


class SessionRegistry:
    """Creates sessions within the limits and finds them again; owns no transport."""

    def __init__(self, ctx: ServerContext) -> None:
        self.ctx = ctx
        self._by_id: dict[int, Session] = {}
        self._by_token: dict[int, Session] = {}
        self._next_id = 1
        self.accepting = True
        #: Called with each session as it closes (e.g. the UDP endpoint drops its hello cache).
        self.on_forget: list[Callable[[Session], None]] = []
        #: Counters of sessions that have closed, so the server's totals never go back.
        self._retired: dict[str, int] = dict.fromkeys(SESSION_TOTALS, 0)
        ctx.report = self.stats
        ctx.ledger.live = self.live

    def __len__(self) -> int:
        return len(self._by_id)

    def __iter__(self) -> Iterator[Session]:
        return iter(list(self._by_id.values()))

    def by_token(self, token: int) -> Session | None:
        return self._by_token.get(token)

    def open(self, hello: Hello) -> Session | ConnectError:
        """A new session for ``hello``, or the reason there is none."""
        cfg = self.ctx.config
        if hello.protocol != PROTOCOL_VERSION:
            return ConnectError(int(ErrorCode.UNSUPPORTED_VERSION),
                                f"client speaks protocol {hello.protocol}, server speaks "
                                f"{PROTOCOL_VERSION}")
        if not self.accepting:
            return ConnectError(int(ErrorCode.SHUTTING_DOWN), "server is shutting down")
        if len(self._by_id) >= cfg.max_sessions:
            return ConnectError(int(ErrorCode.LIMIT),
                                f"server has {cfg.max_sessions} sessions, its limit")
        token = 0
        while token == 0 or token in self._by_token:
            token = secrets.randbits(64)
        sid = self._next_id
        self._next_id += 1
        session = Session(self.ctx, sid, token, hello.name, self._forget)
        self._by_id[sid] = session
        self._by_token[token] = session
        self.ctx.count("sessions_opened")
        return session

    def ack(self, session: Session, datagram_key: bytes = b"") -> ConnectAck:
        cfg = self.ctx.config
        return ConnectAck(
            session=session.id,
            token=session.token,
            heartbeat_ms=cfg.heartbeat_ms,
            timeout_ms=cfg.timeout_ms,
            limits=Limits(cfg.max_packet, cfg.max_channels, cfg.max_batch),
            datagram_key=datagram_key,
        )

    def stats(self) -> dict[str, Any]:
        """``server``: event counters and value totals over every session ever; ``sessions``."""
        sessions = [s.stats() for s in self]
        totals = dict(self._retired)
        for s in sessions:
            for key in SESSION_TOTALS:
                totals[key] += s[key]
        server = {**self.ctx.counters, **totals, "sessions": len(sessions),
                  "handoff_dropped_batches": self.ctx.handoff.dropped_batches}
        return {"server": server, "sessions": sessions}

    def live(self) -> LiveLabels:
        """Clients with an open session, channels bound now: the ledger never folds these."""
        names = {s.name for s in self}
        channels = {channel_key(s.name, b.stats()) for s in self for b in s.inbound.values()}
        channels.update(channel_key(s.name, b.stats()) for s in self for b in s.outbound.values())
        return names, channels

    def _forget(self, session: Session) -> None:
        final = session.stats()
        for key in SESSION_TOTALS:
            self._retired[key] += final[key]
        self.ctx.ledger.retire_session(session.name, final)
        self._by_id.pop(session.id, None)
        self._by_token.pop(session.token, None)
        for listener in self.on_forget:
            listener(session)
