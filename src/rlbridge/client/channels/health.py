"""Per-channel link health: what control code reads to judge one channel's delivery.

``channel.health()`` on an incoming or outgoing bridge channel returns a
:class:`ChannelHealth`: a frozen snapshot of plain ints, built without a lock, a system call
or a wait, so a hard-real-time loop may call it every cycle (it allocates the one object).
Fields a side cannot measure are ``-1``; counters start at 0. docs/policies.md lists where
each number comes from; the server reports the same counters per channel in ``Stats``.
"""

from __future__ import annotations

import msgspec


class ChannelHealth(msgspec.Struct, frozen=True, gc=False):
    """One channel's delivery quality, in ns and counts (``-1``: not measured).

    A msgspec Struct rather than a frozen dataclass: built in C, ~10x cheaper to create,
    which matters to a loop that reads it every cycle; ``msgspec.to_builtins`` makes a dict.
    """

    #: Smoothed round-trip time of the session's link (heartbeats).
    rtt_ns: int
    #: One-way latency: incoming, smoothed age of values on arrival (clock-corrected);
    #: outgoing, half the round trip (the server measures the real one, see ``Stats``).
    one_way_ns: int
    #: RFC 3550 interarrival jitter of this channel's values (incoming only).
    jitter_ns: int
    #: Values that never arrived (sequence gaps).
    lost: int
    #: Values that arrived more than once (redundant UDP) and were dropped.
    duplicates: int
    #: Values displaced from a full buffer before anyone read (or sent) them.
    overwritten: int
    #: Values discarded because a newer one was already there (latest-value delivery,
    #: reordering).
    overtaken: int
    #: Values dropped for being older than the channel's ``max_age_ms``.
    expired: int
    #: Values delivered to the reader (incoming) or written by control code (outgoing).
    values: int
    #: Error bound of the clock offset the ages are corrected by (half the filtered RTT).
    clock_error_ns: int = -1
    #: The server's clock minus this host's, as estimated from heartbeats (0: not yet).
    clock_offset_ns: int = 0
    #: Outgoing: values the server reported as arrived at the first hop (its loss reports;
    #: ``lost`` is then the first-hop loss it reported). Incoming: -1.
    arrived: int = -1
    #: Outgoing with ``max_rate_hz``: the rate limit in force (adaptive: it moves). -1: none.
    rate_limit_hz: int = -1
    #: Values refused for not being of the channel's type: outgoing, at ``write`` (a
    #: ``TypeError``) and by the server (an ``Error(BAD_VALUE)`` counting them), and values
    #: too large to send (over the server's ``max_packet``, or a datagram); server side,
    #: the values of a publish channel it refused.
    rejected: int = 0
    #: Values lost on the middleware side of the server, as the server reports them
    #: (``RosLoss``, every heartbeat period): incoming, messages its ROS subscription's
    #: full queue dropped; outgoing, accepted values ROS refused. ``-1``: none reported yet.
    ros_lost: int = -1
