"""A session's value packets into its publish bindings: the first half of the value path.

Every ``Value``, ``Batch`` and ``Bundle`` a client sends comes through here on its way to the
middleware (:class:`~rlbridge.server.bindings.Inbound`). A value for a channel that is not a
publish channel is counted and answered, ``--max-rate`` cuts what is over the session's limit
(counted, answered at most once a second), and values of the wrong type are answered by the
channel's admission; each part of a bundle is treated as if it had come alone.

This runs once per value on a busy server, so the common case, a ``Value`` part of a bundle
for a publish channel of a session without a rate limit, goes to its binding with no call but
``Inbound.on_value``, and the bundle's parts share one clock reading (they arrived together).
"""

from __future__ import annotations

import time

from rlbridge.server.admission import ValuesRefused
from rlbridge.server.bindings import Inbound
from rlbridge.server.session_owner import SessionOwner
from rlbridge.server.sinks import PacketSink
from rlbridge.wire import Batch, Bundle, ErrorCode, Value

__all__ = ["bundle", "value_packet"]


def bundle(session: SessionOwner, packet: Bundle, via: PacketSink | None) -> None:
    """Each part of a bundle as if it had come alone: one bad part loses only itself."""
    # inlines: value_packet
    inbound = session.inbound
    wall = time.time_ns()
    fast = session.rate is None
    for part in packet.parts:
        if fast and type(part) is Value:
            binding = inbound.get(part.channel)
            if binding is not None:  # value_packet's common case, without the call
                try:
                    binding.on_value(part, wall)
                except ValuesRefused as exc:
                    _refused(session, binding, exc, via)
                continue
        value_packet(session, part.channel, part, via)


def value_packet(session: SessionOwner, channel: int, packet: Value | Batch,
                 via: PacketSink | None) -> None:
    """One value packet (alone, or a bundle's part): publish it or say what is wrong."""
    binding = session.inbound.get(channel)
    if binding is None:
        n = 1 if isinstance(packet, Value) else len(packet.values)
        session.totals.retired["dropped"] += n
        session.ctx.count("dropped_unknown_channel", n)
        code = ErrorCode.UNKNOWN_CHANNEL
        what = "is bound for subscribing" if channel in session.outbound else "is not connected"
        session.error(code, f"channel {channel} {what}; cannot publish on it", channel, via)
        return
    if session.rate is not None:
        admitted = _limit(session, packet, via, binding)
        if admitted is None:
            return
        packet = admitted
    try:
        if isinstance(packet, Value):
            binding.on_value(packet)
        else:
            binding.on_batch(packet)
    except ValuesRefused as exc:
        _refused(session, binding, exc, via)


def _refused(session: SessionOwner, binding: Inbound, exc: ValuesRefused,
             via: PacketSink | None) -> None:
    """Tell the client which of its values the channel's type refused."""
    channel = binding.channel
    session.error(ErrorCode.BAD_VALUE,
                  f"channel {channel} ({binding.spec.msg_type} field "
                  f"{binding.spec.field or '<whole message>'}): {exc.reason}", channel, via,
                  values=exc.count)


def _limit(session: SessionOwner, packet: Value | Batch, via: PacketSink | None,
           binding: Inbound) -> Value | Batch | None:
    """The values ``--max-rate`` lets through (a batch's first ones); the rest counted."""
    rate = session.rate
    assert rate is not None
    now = time.monotonic_ns()
    n = 1 if isinstance(packet, Value) else len(packet.values)
    ok = rate.admit(n, now)
    if ok < n:
        binding.refused += n - ok
        session.ctx.count("rate_dropped", n - ok)
        if rate.should_warn(now):
            session.error(ErrorCode.LIMIT, f"over the server's limit of {rate.rate:g} "
                          f"values per second per session; {rate.dropped} values dropped "
                          "so far", packet.channel, via)
    if ok == n:
        return packet
    if ok == 0 or isinstance(packet, Value):
        return None
    return Batch(packet.channel, packet.first_seq, packet.stamps[:ok], packet.values[:ok])
