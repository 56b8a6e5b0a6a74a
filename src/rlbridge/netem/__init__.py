"""A packet-level network emulator that needs no ``netem`` qdisc.

Two network namespaces joined by TUN devices and a user-space relay that delays, drops
and rate-limits IP packets per direction, so real kernel TCP and UDP can be measured
over an impaired link on machines whose kernel lacks ``sch_netem``.  See ``docs/netem.md``.

Importing this package is cheap and has no side effects; nothing touches the network
until :meth:`EmulatedLink.start` (or ``with EmulatedLink(...)``).
"""

from rlbridge.netem.availability import emulator_unavailable_reason
from rlbridge.netem.impairment import (
    Direction,
    DropReason,
    GilbertElliott,
    Impairment,
    PathModel,
    split_direction,
)
from rlbridge.netem.link import EmulatedLink
from rlbridge.netem.link_settings import Side
from rlbridge.netem.netns import StaleNamespace, cleanup_stale_namespaces, find_stale_namespaces
from rlbridge.netem.relay_process import RelayError
from rlbridge.netem.stats import DirectionStats, LinkStats

__all__ = [
    "Direction",
    "DirectionStats",
    "DropReason",
    "EmulatedLink",
    "GilbertElliott",
    "Impairment",
    "LinkStats",
    "PathModel",
    "RelayError",
    "Side",
    "StaleNamespace",
    "cleanup_stale_namespaces",
    "emulator_unavailable_reason",
    "find_stale_namespaces",
    "split_direction",
]
