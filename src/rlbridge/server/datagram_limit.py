"""What the server does with a control packet too large for any datagram.

A UDP datagram carries at most ``MAX_DATAGRAM`` (65 507) bytes; a ``Stats`` answer on a server
with some thousand topics, or a service's large response, can be more. ``sendto`` would fail and
the event loop swallow the error, so the packet vanished and its client waited out its patience.
The UDP sink (server/sinks.py) hands such a packet here instead: it is counted
(``udp_too_large_out``), the operator hears of it (one line per interval), and the answer the
client waits for becomes a small ``TOO_LARGE`` refusal that says to ask over TCP. A packet that
answers nothing the client could retry (a ``ServiceRequest``, a ``TopicAck``: the binding
exists) is only counted and logged.
"""

from __future__ import annotations

from rlbridge.server.context import ServerContext
from rlbridge.wire import MAX_DATAGRAM, Error, ErrorCode, GoalResult, Packet, ServiceResult, Stats


def too_large_answer(packet: Packet, size: int) -> Packet | None:
    """The small packet that answers in place of ``packet`` (``size`` bytes as a datagram), or
    None when nothing should."""
    reason = (f"the {type(packet).__name__} answer of {size} bytes does not fit a datagram "
              f"({MAX_DATAGRAM} at most): ask over TCP")
    code = int(ErrorCode.TOO_LARGE)
    if isinstance(packet, Stats):
        return Error(code, reason)
    if isinstance(packet, ServiceResult):
        return ServiceResult(packet.call, code, None, reason)
    if isinstance(packet, GoalResult):  # status 0: the goal's end is lost (protocol.md 6)
        return GoalResult(packet.channel, 0, None, reason)
    return None


def refuse_too_large(ctx: ServerContext, who: str, packet: Packet, size: int) -> Packet | None:
    """Count and log a packet of ``who`` (``session 3 (arm)``) too large for a datagram; what
    to send instead (:func:`too_large_answer`)."""
    ctx.count("udp_too_large_out")
    ctx.notices.warn("datagram too large", f"{who}: a {type(packet).__name__} of {size} bytes "
                     f"does not fit a datagram ({MAX_DATAGRAM} at most); not sent")
    return too_large_answer(packet, size)
