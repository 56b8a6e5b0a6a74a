"""The client SDK's CSP layer: ring buffers, channels, processes and the periodic timer.

``from rlbridge.csp import Channel, ChannelClosed``. Nothing here imports asyncio: this is
the hard-real-time side. The network side of the SDK is :class:`rlbridge.Bridge`.
"""

from rlbridge.csp.channel import Channel, Doorbell
from rlbridge.csp.process import (
    Code,
    Parallel,
    PriParallel,
    Process,
    Recursion,
    Sequential,
)
from rlbridge.csp.ring import EMPTY, MpscRing, SpscRing
from rlbridge.csp.statistics import ChannelStatistics
from rlbridge.csp.timer import PeriodicTimer, Timed
from rlbridge.errors import (
    ChannelClosed,
    ChannelError,
    ChannelMisuseError,
    NoValueYet,
    RealTimeWarning,
    WouldBlock,
)

__all__ = [
    "EMPTY", "Channel", "ChannelClosed", "ChannelError", "ChannelMisuseError",
    "ChannelStatistics", "Code", "Doorbell", "MpscRing", "NoValueYet", "Parallel",
    "PeriodicTimer", "PriParallel", "Process", "RealTimeWarning", "Recursion", "Sequential",
    "SpscRing", "Timed", "WouldBlock",
]
