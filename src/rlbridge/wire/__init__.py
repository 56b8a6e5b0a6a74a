"""The rlbridge wire protocol, sans-IO: bytes in, typed packets out, and back.

Nothing here touches a socket, a thread, an event loop or a clock; time is a parameter. The
server's TCP and UDP paths and the client SDK all drive this same code.
"""

from rlbridge.errors import (
    ErrorCode,
    LocalProtocolError,
    RemoteError,
    RemoteProtocolError,
    RlbridgeError,
    error_from_code,
)
from rlbridge.wire.codec import (
    DATAGRAM_HEADER,
    DEFAULT_MAX_PACKET,
    FRAME_HEADER,
    MAGIC,
    MAX_DATAGRAM,
    FrameDecoder,
    Malformed,
    PacketCodec,
)
from rlbridge.wire.packets import (
    PROTOCOL_VERSION,
    AuthChallenge,
    AuthProof,
    Batch,
    Bundle,
    ChannelLoss,
    ConnectAck,
    ConnectError,
    Credit,
    Disconnect,
    Error,
    GoalCancel,
    GoalResult,
    GoalSend,
    Heartbeat,
    Hello,
    Limits,
    LossReport,
    Packet,
    RosLoss,
    ServiceCall,
    ServiceOffer,
    ServiceReply,
    ServiceRequest,
    ServiceResult,
    Stats,
    TopicAck,
    TopicClose,
    TopicConnect,
    TopicError,
    Value,
)

__all__ = [
    "DATAGRAM_HEADER", "DEFAULT_MAX_PACKET", "FRAME_HEADER", "MAGIC", "MAX_DATAGRAM",
    "PROTOCOL_VERSION", "AuthChallenge", "AuthProof",
    "Batch", "Bundle", "ChannelLoss", "ConnectAck", "ConnectError", "Credit", "Disconnect",
    "Error", "ErrorCode", "FrameDecoder", "GoalCancel", "GoalResult", "GoalSend", "Heartbeat",
    "Hello", "Limits", "LocalProtocolError", "LossReport", "Malformed", "Packet", "PacketCodec",
    "RemoteError", "RemoteProtocolError", "RlbridgeError", "RosLoss", "ServiceCall",
    "ServiceOffer", "ServiceReply", "ServiceRequest", "ServiceResult", "Stats", "TopicAck",
    "TopicClose", "TopicConnect", "TopicError", "Value",
    "error_from_code",
]
