"""Action goals on the client side: a feedback channel, a result to wait for, a cancel.

``Bridge.send_goal`` registers the goal's feedback channel like a subscription's (the server
sends feedback as ``Value`` packets on the goal's channel, so the receive thread delivers them
the same way) and waits for the action server to accept the goal. The ``GoalResult`` packet
completes :meth:`Goal.result`. A goal is not sent again after a reconnect: the session that
ended cancelled it on the server, and :meth:`Goal.result` raises ``ConnectionClosed``.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rlbridge.errors import ConnectionClosed
from rlbridge.wire import GoalCancel, GoalResult

if TYPE_CHECKING:
    from rlbridge.csp.bridge_channels import IncomingChannel
    from rlbridge.csp.session_owner import SessionOwner

#: ROS 2 ``action_msgs/msg/GoalStatus`` codes of a goal's end.
STATUS_NAMES = {0: "unknown", 1: "accepted", 2: "executing", 3: "canceling", 4: "succeeded",
                5: "canceled", 6: "aborted"}


class Goal:
    """An accepted goal: ``feedback`` (a channel of dicts), ``result()``, ``cancel()``."""

    def __init__(self, conn: SessionOwner, channel: int, action: str,
                 feedback: IncomingChannel) -> None:
        self._conn = conn
        self._generation = conn.generation
        self.channel_id = channel
        self.action = action
        #: Feedback messages as dicts, in order (a blocking channel: ``read(timeout=...)``).
        self.feedback = feedback
        self._done = threading.Event()
        self._answer: GoalResult | None = None
        #: Called once the goal ended (the bridge forgets its feedback channel).
        self.on_finish: Callable[[], None] | None = None

    @property
    def status(self) -> str:
        """``executing`` until the end, then ``succeeded``, ``canceled`` or ``aborted``."""
        answer = self._answer
        return "executing" if answer is None else STATUS_NAMES.get(answer.status, "unknown")

    def result(self, timeout: float | None = None) -> dict[str, Any]:
        """Wait for the goal's end; its result (a dict). ``status`` says how it ended.

        Raises ``TimeoutError`` if it has not ended within ``timeout`` seconds and
        ``ConnectionClosed`` if the session ended first.
        """
        if not self._done.wait(timeout):
            raise TimeoutError(f"goal on {self.action} still running after {timeout} s")
        answer = self._answer
        if answer is None:
            raise ConnectionClosed(f"session ended before the goal on {self.action} did: "
                                   f"{self._conn.close_reason}")
        return answer.result or {}

    def cancel(self) -> None:
        """Ask the action server to cancel the goal (the result then says if it did)."""
        if self._done.is_set():
            return
        if self._conn.generation != self._generation or not self._conn.up:
            raise ConnectionClosed("the session this goal was sent in has ended")
        self._conn.send_control(GoalCancel(self.channel_id))

    def finish(self, packet: GoalResult | None) -> None:
        """The receive thread got the end (``None``: the session ended first)."""
        self._answer = packet
        self._done.set()
        with contextlib.suppress(Exception):
            self.feedback.close()
        if self.on_finish is not None:
            self.on_finish()
