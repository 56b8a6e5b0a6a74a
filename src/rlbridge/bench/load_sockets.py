"""The kernel's view of a process's UDP sockets: datagrams dropped for a full receive buffer.

A UDP datagram that arrives while its socket's receive queue is full is dropped by the kernel,
before any user code sees it. The protocol notices later (a sequence gap at the server for hop
1, at the client for hop 2), but only the kernel knows it was *this* socket's buffer: Linux
counts it per socket (the ``drops`` column of ``/proc/net/udp``) as well as machine-wide
(``UdpRcvbufErrors``, which every other program on a shared machine also adds to). The load
benchmark reads the per-socket counters of the processes it started, so the loss it reports
per stage is its own.

Linux only; elsewhere (or for a process that has gone) the readers return nothing.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class UdpSocketState:
    """One UDP socket as ``/proc/<pid>/net/udp`` shows it."""

    inode: int
    local_port: int
    #: Bytes queued for the process to read (the kernel's accounting, with overhead).
    rx_queue: int
    #: Datagrams dropped since the socket opened (receive buffer full, or a bad checksum).
    drops: int


def parse_proc_net_udp(text: str) -> dict[int, UdpSocketState]:
    """Sockets by inode from the text of ``/proc/net/udp`` or ``udp6``.

    Columns: ``sl local rem st tx_queue:rx_queue tr:tm->when retrnsmt uid timeout inode ref
    pointer drops``; addresses and queues are hex.
    """
    sockets: dict[int, UdpSocketState] = {}
    for line in text.splitlines()[1:]:
        f = line.split()
        if len(f) < 13:
            continue
        inode = int(f[9])
        sockets[inode] = UdpSocketState(inode=inode, local_port=int(f[1].rsplit(":", 1)[1], 16),
                                        rx_queue=int(f[4].split(":")[1], 16), drops=int(f[12]))
    return sockets


def socket_inodes(pid: int) -> set[int]:
    """Inodes of the sockets process ``pid`` holds open (its ``fd`` links ``socket:[N]``)."""
    inodes: set[int] = set()
    with contextlib.suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(int(link[8:-1]))
    return inodes


def udp_sockets(pid: int) -> list[UdpSocketState]:
    """Every UDP socket process ``pid`` holds open, as its network namespace reports them."""
    held = socket_inodes(pid)
    found: list[UdpSocketState] = []
    for name in ("udp", "udp6"):
        with contextlib.suppress(OSError), open(f"/proc/{pid}/net/{name}") as f:
            found += [s for inode, s in parse_proc_net_udp(f.read()).items() if inode in held]
    return found


def udp_queued(pid: int) -> int:
    """Bytes waiting in the receive queues of process ``pid``'s UDP sockets (kernel memory)."""
    return sum(s.rx_queue for s in udp_sockets(pid))


def udp_drops(pids: list[int]) -> int:
    """Datagrams the kernel dropped on the UDP sockets of ``pids`` (receive buffers full)."""
    return sum(s.drops for pid in pids for s in udp_sockets(pid))
