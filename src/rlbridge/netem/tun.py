"""One end of the emulated wire: a TUN device inside a namespace, configured point-to-point.

A TUN device created without ``IFF_VNET_HDR`` hands user space one whole IP packet per
``read`` (no GSO/GRO super-packets), so every packet the relay sees is at most the MTU
and the emulated link fragments and segments exactly like a real one with that MTU.
``IFF_NO_PI`` drops the 4-byte packet-information header: the relay moves raw IP packets.

The device is non-persistent: it exists while a descriptor from :func:`open_tun` is open,
so when the relay process (which ends up owning the descriptors) exits, the devices go.
"""

from __future__ import annotations

import fcntl
import json
import os
import struct

from rlbridge.netem.netns import call_in_namespace, run_ip

TUN_DEVICE = "/dev/net/tun"
_TUNSETIFF = 0x400454CA
_IFF_TUN = 0x0001
_IFF_NO_PI = 0x1000
IFNAMSIZ = 16


def open_tun(namespace: str, ifname: str) -> int:
    """Create TUN device ``ifname`` in ``namespace``; return its non-blocking descriptor.

    The namespace of a TUN device is the one current when ``/dev/net/tun`` is opened, so
    the open happens in a helper thread that has joined ``namespace``.
    """
    if len(ifname.encode()) >= IFNAMSIZ:
        raise ValueError(f"interface name {ifname!r} is longer than {IFNAMSIZ - 1} bytes")

    def create() -> int:
        fd = os.open(TUN_DEVICE, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)
        try:
            ifreq = struct.pack("16sH22x", ifname.encode(), _IFF_TUN | _IFF_NO_PI)
            fcntl.ioctl(fd, _TUNSETIFF, ifreq)
        except BaseException:
            os.close(fd)
            raise
        return fd

    return call_in_namespace(namespace, create)


def configure_point_to_point(
    namespace: str, ifname: str, *, local: str, peer: str, mtu: int, txqueuelen: int = 1000
) -> None:
    """Address ``ifname`` as ``local peer PEER``, set MTU and bring it up.

    ``peer`` installs the host route to the other namespace through the TUN.  IPv6
    address generation is switched off so the kernel sends no router solicitations or MLD
    reports: the only packets on the wire are the ones the program under test sends, which
    keeps the seeded loss pattern reproducible.
    """
    run_ip(
        "-n", namespace, "link", "set", "dev", ifname,
        "mtu", str(mtu), "txqueuelen", str(txqueuelen), "addrgenmode", "none",
    )  # fmt: skip
    run_ip("-n", namespace, "addr", "add", local, "peer", peer, "dev", ifname)
    run_ip("-n", namespace, "link", "set", "dev", ifname, "up")


def tx_dropped(namespace: str, ifname: str) -> int:
    """Packets the kernel in ``namespace`` dropped on ``ifname`` before the relay read them.

    A TUN device queues at most ``txqueuelen`` packets for user space and drops the rest
    (counted as transmit drops), for instance when a sender floods the link faster than
    the relay reads.  Those drops never reach the relay's own counters.
    """
    proc = run_ip("-n", namespace, "-s", "-j", "link", "show", "dev", ifname)
    (info,) = json.loads(proc.stdout)
    return int(info["stats64"]["tx"]["dropped"])
