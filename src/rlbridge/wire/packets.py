"""Packet types: what the wire carries, as frozen, tagged msgspec Structs.

Every packet body is a MessagePack array whose first element is the packet's integer tag
(``array_like=True``, ``tag=N``), so decoding picks the class and validates every field in one
C call: a packet that decodes is well-formed. Field order is the wire order: append new fields
at the end with defaults, never reorder (docs/protocol.md is the normative description).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Protocol, cast

import msgspec

PROTOCOL_VERSION = 1

U16 = Annotated[int, msgspec.Meta(ge=0, le=0xFFFF)]
U32 = Annotated[int, msgspec.Meta(ge=0, le=0xFFFF_FFFF)]
U64 = Annotated[int, msgspec.Meta(ge=0)]  # msgspec bounds stop at int64; msgpack caps at 2**64
I64 = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]
Name = Annotated[str, msgspec.Meta(max_length=128)]
TopicName = Annotated[str, msgspec.Meta(min_length=1, max_length=256)]
TypeName = Annotated[str, msgspec.Meta(min_length=1, max_length=128)]
FieldPath = Annotated[str, msgspec.Meta(min_length=1, max_length=128)]
#: The most characters a reason carries on the wire (docs/protocol.md, section 4).
REASON_MAX = 1024
#: A reason's type: any length on decode, because :class:`_Explained` cuts it to
#: :data:`REASON_MAX` there as on construction: a reason is for people, so a peer's long one
#: costs its tail, not the packet (a client waiting for a refusal still gets it).
Reason = str
Bytes32 = Annotated[bytes, msgspec.Meta(max_length=64)]

Direction = Literal["subscribe", "publish"]
Transport = Literal["tcp", "udp"]
Reliability = Literal["reliable", "best_effort"]
Durability = Literal["volatile", "transient_local", "match"]


class _Packet(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=False):
    """Base: array-encoded, immutable. Unknown trailing fields are ignored (forward compat)."""


def cut_reason(reason: str) -> str:
    """``reason`` if it fits in :data:`REASON_MAX` characters, else its head and an ellipsis
    that show it was cut (the head is what says what went wrong)."""
    if len(reason) <= REASON_MAX:
        return reason
    return reason[: REASON_MAX - 1] + "\u2026"


class _Explained(_Packet, frozen=True):
    """Base of the packets with a ``reason``: it is cut (:func:`cut_reason`) wherever the
    packet is made, by a constructor or by the decoder, so no sender needs to remember to."""

    def __post_init__(self) -> None:
        reason = cast("_HasReason", self).reason
        if len(reason) > REASON_MAX:
            msgspec.structs.force_setattr(self, "reason", cut_reason(reason))


class _HasReason(Protocol):
    """What every subclass of :class:`_Explained` has (each declares it in its wire order)."""

    reason: str


class Limits(_Packet, frozen=True):
    """What the server accepts; a client that respects these never meets a LIMIT error."""

    max_packet: U32
    max_channels: U32
    max_batch: U32


class Hello(_Packet, tag=1, frozen=True):
    """Client -> server, first packet on TCP and on a UDP-only session: who and which version."""

    protocol: U16
    name: Name
    auth: Bytes32 = b""


class ConnectAck(_Packet, tag=2, frozen=True):
    """Server -> client: the session exists. ``token`` must be in every UDP datagram."""

    session: U32
    token: U64
    heartbeat_ms: U32
    timeout_ms: U32
    limits: Limits
    #: Over TLS: the 32-byte secret the session's datagram keys derive from (wire/seal.py);
    #: empty otherwise (a pre-shared key derives them from the handshake instead).
    datagram_key: Bytes32 = b""


class ConnectError(_Explained, tag=3, frozen=True):
    """Server -> client: no session (version, limit, auth); the server closes after sending it."""

    code: U16
    reason: Reason


class TopicConnect(_Packet, tag=4, frozen=True):
    """Client -> server: bind channel ``channel`` to a middleware topic, in one direction."""

    channel: U32
    direction: Direction
    topic: TopicName
    msg_type: TypeName
    field: FieldPath | None = "data"
    transport: Transport = "tcp"
    buffer_size: U32 = 1
    reliability: Reliability | None = None
    depth: U16 = 10
    max_age_ms: U32 = 0
    redundancy: Annotated[int, msgspec.Meta(ge=0, le=16)] = 0
    latest: bool = False
    #: Subscribe: the client grants credit for this channel (``Credit`` packets); the server
    #: sends at most ``buffer_size`` values beyond what the client has consumed. Publish:
    #: the client honours the credit the server grants (``TopicAck.credit``, ``Credit``).
    flow: bool = False
    #: Publish: the client wants ``LossReport`` packets for this channel (first-hop counts).
    loss_report: bool = False
    #: ``transient_local``: a latched topic (late subscribers get the last ``depth`` values);
    #: ``match`` (subscribe only): the durability and reliability of the topic's publishers.
    durability: Durability = "volatile"


class TopicAck(_Packet, tag=5, frozen=True):
    """Server -> client: the binding exists; ``initial`` is a fresh message's field value."""

    channel: U32
    msg_type: TypeName
    initial: Any = None
    #: The JSON Schema (draft 2020-12, as a map) of the values the channel accepts, so a
    #: client can refuse a wrong value where it is written (``None``: not given).
    schema: dict[str, Any] | None = None
    #: A flow-controlled publish channel (``TopicConnect.flow``): the first credit, the
    #: sequence number the client may send up to, not including it. None: no credit limit.
    credit: U64 | None = None


class TopicError(_Explained, tag=6, frozen=True):
    """Server -> client: the binding was refused; ``reason`` names the problem for a person."""

    channel: U32
    code: U16
    reason: Reason


class TopicClose(_Packet, tag=7, frozen=True):
    """Client -> server: unbind a channel; its publisher or listener goes away."""

    channel: U32


class Value(_Packet, tag=8, frozen=True):
    """One value of one channel. ``stamp_ns`` is the sender's CLOCK_REALTIME when written."""

    channel: U32
    seq: U64
    stamp_ns: I64
    value: Any


class Batch(_Packet, tag=9, frozen=True):
    """Many values of one channel, sequence numbers ``first_seq``, ``first_seq + 1``, ..."""

    channel: U32
    first_seq: U64
    stamps: list[I64]
    values: list[Any]

    def __post_init__(self) -> None:
        if len(self.stamps) != len(self.values):
            raise ValueError(
                f"batch has {len(self.values)} values but {len(self.stamps)} stamps"
            )


class Heartbeat(_Packet, tag=10, frozen=True):
    """Either way, every heartbeat period: liveness, and RTT by echoing the peer's stamp."""

    sent_ns: I64
    echo_ns: I64 = 0
    #: The sender's CLOCK_REALTIME when sending (0: not given); the peer's clock-offset
    #: estimate (wire/clock.py) uses it with the two echo fields below, NTP-style.
    wall_ns: I64 = 0
    #: The peer's last ``wall_ns`` and the sender's CLOCK_REALTIME when it arrived.
    echo_wall_ns: I64 = 0
    echo_rx_wall_ns: I64 = 0


class Disconnect(_Explained, tag=11, frozen=True):
    """Either way: an orderly goodbye, so the peer need not wait for the watchdog."""

    code: U16 = 0
    reason: Reason = ""


class Error(_Explained, tag=12, frozen=True):
    """Either way: a packet was refused; the session goes on unless a Disconnect follows."""

    code: U16
    reason: Reason
    channel: U32 | None = None
    #: ``BAD_VALUE``: how many values of the refused packet were refused (the others were
    #: published); 0 for every other error. The client counts them in ``health().rejected``.
    values: U32 = 0


class Stats(_Packet, tag=13, frozen=True):
    """Client -> server asks (``body`` empty); server -> client answers with counters."""

    body: dict[str, Any] = msgspec.field(default_factory=dict)


Nonce = Annotated[bytes, msgspec.Meta(min_length=16, max_length=16)]
Mac = Annotated[bytes, msgspec.Meta(min_length=32, max_length=32)]


class AuthChallenge(_Packet, tag=14, frozen=True):
    """Server -> client, instead of ConnectAck when a key is required (docs/security.md).

    ``nonce`` is the server's fresh nonce; ``proof`` shows the server knows the key.
    """

    nonce: Nonce
    proof: Mac


class AuthProof(_Packet, tag=15, frozen=True):
    """Client -> server: HMAC-SHA256 of the handshake transcript under the pre-shared key."""

    proof: Mac


ServiceName = Annotated[str, msgspec.Meta(min_length=1, max_length=256)]


class ServiceCall(_Packet, tag=20, frozen=True):
    """Client -> server: call a middleware service; answered by one ``ServiceResult``.

    ``call`` is the client's number for the call (its answer carries it back); ``request`` is
    a map of the request type's fields; the server gives up after ``timeout_ms``.
    """

    call: U32
    service: ServiceName
    srv_type: TypeName
    request: dict[str, Any]
    timeout_ms: U32 = 5000


class ServiceResult(_Explained, tag=21, frozen=True):
    """Server -> client: the answer to ``ServiceCall`` ``call``: ``code`` 0 and ``response``,
    or an error code (``NO_SERVICE``, ``TIMEOUT``, ``BAD_VALUE``, ...) and ``reason``."""

    call: U32
    code: U16 = 0
    response: dict[str, Any] | None = None
    reason: Reason = ""


class ServiceOffer(_Packet, tag=22, frozen=True):
    """Client -> server: provide ``service`` on channel ``channel`` (answered like a
    topic-connect: ``TopicAck`` or ``TopicError``; ``TopicClose`` withdraws it)."""

    channel: U32
    service: ServiceName
    srv_type: TypeName


class ServiceRequest(_Packet, tag=23, frozen=True):
    """Server -> client: a request to the service offered on ``channel``; answer it with a
    ``ServiceReply`` carrying the same ``request_id``."""

    channel: U32
    request_id: U64
    request: dict[str, Any]


class ServiceReply(_Explained, tag=24, frozen=True):
    """Client -> server: the response to ``request_id`` (``code`` 0), or the provider's failure
    (``code`` ``SERVICE_FAILED`` and ``reason``)."""

    channel: U32
    request_id: U64
    code: U16 = 0
    response: dict[str, Any] | None = None
    reason: Reason = ""


class GoalSend(_Packet, tag=25, frozen=True):
    """Client -> server: send an action goal; channel ``channel`` then carries its feedback
    (``Value`` packets of dicts). Answered with ``TopicAck`` (accepted) or ``TopicError``
    (``NO_SERVICE``, ``GOAL_REJECTED``, ...); the end comes as ``GoalResult``."""

    channel: U32
    action: ServiceName
    action_type: TypeName
    goal: dict[str, Any]
    timeout_ms: U32 = 5000


class GoalCancel(_Packet, tag=26, frozen=True):
    """Client -> server: ask the action server to cancel the goal on ``channel``."""

    channel: U32


class GoalResult(_Explained, tag=27, frozen=True):
    """Server -> client: the goal on ``channel`` ended: ``status`` as ROS 2's GoalStatus
    (4 succeeded, 5 canceled, 6 aborted; 0 with ``reason``: lost) and its ``result``."""

    channel: U32
    status: U16
    result: dict[str, Any] | None = None
    reason: Reason = ""


class RosLoss(_Packet, tag=28, frozen=True):
    """Server -> client: the total of values of ``channel`` lost on the middleware side so
    far (a ROS subscription's full queue, values rmw refused); sent when it grows, at most
    once per heartbeat period. The client shows it as ``health().ros_lost``."""

    channel: U32
    ros_lost: U64


# Tags of new packet kinds are allocated per line of work, so that parallel branches never
# reuse a number (tags are the wire format): 16-19 security (TLS/AEAD/authorization),
# 20-29 ROS 2 services/actions/parameters, 30-31 value rejection, 32-33 UDP bundles,
# 34-37 loss feedback and flow control. Add new kinds at the end of the union below.
class Bundle(_Packet, tag=32, frozen=True):
    """Values of several channels in one datagram; each part is a whole ``Value`` or ``Batch``.

    One datagram per send round instead of one per channel: the header, the system call and
    the wake-up are paid once for every channel (docs/protocol.md 6.16). A receiver treats each
    part exactly as if it had arrived alone.
    """

    parts: list[Value | Batch]


class Credit(_Packet, tag=34, frozen=True):
    """The receiving end of a flow-controlled channel -> its sender: send up to ``limit``.

    The sender may send the values numbered below ``limit`` (cumulative, never decreasing:
    a credit that arrives late or twice changes nothing). Subscriber -> server for a
    subscribe channel, server -> publisher for a publish channel (docs/protocol.md 10.5).
    """

    channel: U32
    limit: U64


class ChannelLoss(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=False):
    """One publish channel's first hop, as the server saw it (counts since it was bound)."""

    channel: U32
    #: Values that arrived (new ones; duplicates and overtaken values not counted).
    received: U64
    #: Values that never arrived: gaps in the sequence numbers.
    lost: U64
    #: One past the highest sequence number that arrived (0: none yet).
    next_seq: U64
    #: Values the server's own rate limit (``--max-rate``) refused.
    refused: U64 = 0


class LossReport(_Packet, tag=35, frozen=True):
    """Server -> client, every heartbeat period while counts changed: the first hop per channel.

    Counts are cumulative, so a lost report costs nothing but time (docs/protocol.md 10.6).
    """

    channels: Annotated[list[ChannelLoss], msgspec.Meta(max_length=256)]


Packet = (
    Hello | ConnectAck | ConnectError | TopicConnect | TopicAck | TopicError | TopicClose
    | Value | Batch | Heartbeat | Disconnect | Error | Stats | AuthChallenge | AuthProof
    | Bundle | Credit | LossReport
    | ServiceCall | ServiceResult | ServiceOffer | ServiceRequest | ServiceReply
    | GoalSend | GoalCancel | GoalResult | RosLoss
)

#: Packets a value path carries; everything else is control.
DATA_PACKETS = (Value, Batch)
