"""Messages on the control channel between an EmulatedLink and its relay process.

The channel is a ``SOCK_SEQPACKET`` unix socket pair: one datagram is one message, so
no framing is needed.  The link sends a request and waits for exactly one reply.  When
the link side closes (normally, or because the parent process died), the relay reads EOF
and exits; that is what keeps a relay from outliving the process that started it.
"""

from __future__ import annotations

import msgspec

from rlbridge.netem.impairment import Impairment
from rlbridge.netem.stats import LinkStats

MAX_MESSAGE_BYTES = 65536


class SetImpairments(msgspec.Struct, frozen=True, tag=True):
    """Replace the impairment of both directions (packets in flight keep their times)."""

    a_to_b: Impairment
    b_to_a: Impairment


class GetStats(msgspec.Struct, frozen=True, tag=True):
    """Ask for a :class:`LinkStats` snapshot."""


class Stop(msgspec.Struct, frozen=True, tag=True):
    """Ask the relay to exit; packets still in flight are discarded (as on link-down)."""


class Ready(msgspec.Struct, frozen=True, tag=True):
    """Sent once by the relay when its loop runs."""

    pid: int


class Ok(msgspec.Struct, frozen=True, tag=True):
    """Positive reply to SetImpairments and Stop."""


class StatsReply(msgspec.Struct, frozen=True, tag=True):
    """Reply to GetStats."""

    stats: LinkStats


class Failed(msgspec.Struct, frozen=True, tag=True):
    """The relay could not do what was asked; ``message`` says why."""

    message: str


Request = SetImpairments | GetStats | Stop
Reply = Ready | Ok | StatsReply | Failed

_request_decoder: msgspec.json.Decoder[Request] = msgspec.json.Decoder(Request)
_reply_decoder: msgspec.json.Decoder[Reply] = msgspec.json.Decoder(Reply)
_encoder = msgspec.json.Encoder()


def encode(message: Request | Reply) -> bytes:
    """Encode one message as one datagram."""
    return _encoder.encode(message)


def decode_request(data: bytes) -> Request:
    """Decode a request; raises ``msgspec.ValidationError``/``DecodeError`` on bad input."""
    return _request_decoder.decode(data)


def decode_reply(data: bytes) -> Reply:
    """Decode a reply; raises ``msgspec.ValidationError``/``DecodeError`` on bad input."""
    return _reply_decoder.decode(data)
