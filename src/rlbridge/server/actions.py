"""A session's action goals: sent for its client, their feedback and result sent back.

``adapter.send_goal`` blocks until the action server accepts or rejects the goal, so it runs
on a worker thread like a service call; the answer is a ``TopicAck`` or ``TopicError`` on
the goal's channel, as for a topic-connect. Feedback (on the executor thread) hops to the
event loop and goes out as ``Value`` packets on that channel, numbered like any channel's
values; the end goes out as one ``GoalResult``. ``GoalCancel`` asks the action server to
cancel; a session that ends cancels its goals still running.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rlbridge.adapters.base import GoalHandle
from rlbridge.server.services import MAX_CALLS
from rlbridge.server.sinks import PacketSink
from rlbridge.server.worker_calls import Failure, channel_in_use, off_loop, outcome, timeout_s
from rlbridge.wire import ErrorCode, GoalResult, GoalSend, TopicAck, TopicError, Value

if TYPE_CHECKING:
    from rlbridge.server.session_owner import SessionOwner

log = logging.getLogger("rlbridge.server")


@dataclass(eq=False)
class _Goal:
    request: GoalSend
    handle: GoalHandle | None = None
    feedback: int = 0
    cancel_asked: bool = False
    ended: bool = False

    def stats(self) -> dict[str, Any]:
        return {"direction": "goal", "topic": self.request.action,
                "action_type": self.request.action_type, "values_out": self.feedback}


class SessionGoals:
    """Goals of one session, by channel; see the module docstring."""

    def __init__(self, session: SessionOwner) -> None:
        self._session = session
        self.goals: dict[int, _Goal] = {}
        self.sent = 0

    def send(self, req: GoalSend, via: PacketSink | None, in_use: bool) -> None:
        s = self._session
        ch = req.channel
        if in_use or ch in self.goals:
            s.send_control(channel_in_use(ch), via)
            return
        if len(self.goals) >= MAX_CALLS:
            s.send_control(TopicError(ch, int(ErrorCode.LIMIT), f"this session already has "
                                      f"{MAX_CALLS} goals in flight"), via)
            return
        goal = self.goals[ch] = _Goal(req)
        self.sent += 1
        s.ctx.count("goals_sent")
        loop = s.ctx.loop

        def feedback(value: dict[str, Any]) -> None:
            loop.call_soon_threadsafe(self._feedback, goal, value)

        def done(status: int, result: dict[str, Any]) -> None:
            loop.call_soon_threadsafe(self._done, goal, status, result, "")

        off_loop(s.ctx, lambda f: self._answered(goal, f, via), s.ctx.adapter.send_goal,
                 req.action, req.action_type, req.goal, feedback, done,
                 timeout_s(req.timeout_ms))

    def _answered(self, goal: _Goal, future: Future[GoalHandle], via: PacketSink | None) -> None:
        s = self._session
        ch = goal.request.channel
        handle = outcome(future, f"sending a goal to {goal.request.action}")
        if isinstance(handle, Failure):
            self.goals.pop(ch, None)
            s.send_control(TopicError(ch, int(handle.code), handle.reason), via)
            return
        goal.handle = handle
        if s.closed or goal.cancel_asked:  # ended or cancelled while it was being accepted
            handle.cancel()
        if not s.closed:
            s.send_control(TopicAck(ch, goal.request.action_type, None), via)

    def _feedback(self, goal: _Goal, value: dict[str, Any]) -> None:
        if goal.ended or self._session.closed:
            return
        seq = goal.feedback
        goal.feedback += 1
        self._session.send_control(Value(goal.request.channel, seq, time.time_ns(), value))

    def _done(self, goal: _Goal, status: int, result: dict[str, Any] | None,
              reason: str) -> None:
        if goal.ended:
            return
        goal.ended = True
        ch = goal.request.channel
        if self.goals.get(ch) is goal:
            del self.goals[ch]
        if not self._session.closed:
            self._session.send_control(GoalResult(ch, status, result, reason))

    def cancel(self, channel: int, via: PacketSink | None) -> None:
        goal = self.goals.get(channel)
        if goal is None:
            self._session.error(ErrorCode.UNKNOWN_CHANNEL,
                                f"channel {channel} has no goal running", channel, via)
            return
        goal.cancel_asked = True
        if goal.handle is not None:
            goal.handle.cancel()

    def close(self) -> None:
        """The session ends: cancel every goal still running."""
        goals, self.goals = list(self.goals.values()), {}
        for goal in goals:
            goal.ended = True
            if goal.handle is not None:
                try:
                    goal.handle.cancel()
                except Exception:
                    log.exception("cancelling a goal of %s", goal.request.action)

    def channel_stats(self) -> dict[str, dict[str, Any]]:
        return {str(c): g.stats() for c, g in self.goals.items()}
