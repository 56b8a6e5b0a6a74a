"""Socket buffer sizes: ask the kernel, and say what it granted.

A UDP socket's receive buffer is where datagrams wait while the process that reads them is
busy or not scheduled; when it is full the kernel drops what arrives, and only the kernel's
counters know (``/proc/net/udp`` ``drops``, ``UdpRcvbufErrors``). The server's one UDP socket
takes every client's datagrams, so its buffer decides how long a stall it survives without
loss, and how late the values are that wait in it: the kernel counts each datagram's whole
allocation (a 195-byte bundle of ten values takes 832 bytes on loopback) against the buffer,
so the 32 MiB the server asks for by default (64 MiB as the kernel counts) hold about 80,000
such datagrams, 8 s of 100 clients sending 100 bundles/s each (docs/load.md).

Linux caps ``SO_RCVBUF``/``SO_SNDBUF`` requests at ``net.core.rmem_max``/``wmem_max``
silently (many distributions ship 208 KiB). A process with ``CAP_NET_ADMIN`` may go beyond
with ``SO_RCVBUFFORCE``/``SO_SNDBUFFORCE``, which is what the capability is for; anyone else
gets the cap, and :func:`request_buffer` reports it so the server can say which sysctl to
raise (when the size was asked for explicitly), as UDP-heavy programs do. Linux also doubles
the request for its bookkeeping and reports the doubled figure; :class:`BufferGrant` gives
both.
"""

from __future__ import annotations

import contextlib
import socket
import sys
from dataclasses import dataclass
from typing import Literal

Direction = Literal["receive", "send"]

#: Linux option numbers (``socket`` exports them only on some Python builds).
SO_SNDBUFFORCE = getattr(socket, "SO_SNDBUFFORCE", 32)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)

_OPTIONS = {"receive": (socket.SO_RCVBUF, SO_RCVBUFFORCE, "net.core.rmem_max"),
            "send": (socket.SO_SNDBUF, SO_SNDBUFFORCE, "net.core.wmem_max")}


@dataclass(frozen=True)
class BufferGrant:
    """What a socket asked for and got, in the units of the request."""

    direction: Direction
    asked: int
    #: The request as the kernel granted it (Linux: the reported size halved; it doubles).
    got: int
    #: What ``getsockopt`` reports: on Linux the limit on queued bytes with their overhead.
    reported: int
    #: Granted through ``SO_*BUFFORCE`` beyond the sysctl cap (needs ``CAP_NET_ADMIN``).
    forced: bool

    @property
    def capped(self) -> bool:
        return self.got < self.asked

    @property
    def sysctl(self) -> str:
        return _OPTIONS[self.direction][2]

    def describe(self) -> str:
        """One line for a log: asked, got, and how to get the rest if it was capped."""
        text = (f"UDP {self.direction} buffer: asked {self.asked:,} bytes, got {self.got:,}"
                f"{' (forced past ' + self.sysctl + ')' if self.forced else ''}")
        if self.capped:
            text += (f"; capped by {self.sysctl}: raise it (sysctl -w {self.sysctl}="
                     f"{self.asked}) or run with CAP_NET_ADMIN")
        return text


def request_buffer(sock: socket.socket, direction: Direction, size: int) -> BufferGrant:
    """Ask for a ``size``-byte buffer; past the sysctl cap if the process is allowed to.

    Never raises for a refusal: a socket keeps whatever the kernel gave it, and the grant
    says what that is.
    """
    if size <= 0:
        raise ValueError(f"a socket buffer of {size} bytes: give a positive size")
    plain, force, _ = _OPTIONS[direction]
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, plain, size)
    got = _granted(sock, plain)
    forced = False
    if got < size and sys.platform.startswith("linux"):
        try:
            sock.setsockopt(socket.SOL_SOCKET, force, size)
        except OSError:  # EPERM without CAP_NET_ADMIN: keep the capped size
            pass
        else:
            got = _granted(sock, plain)
            forced = True
    return BufferGrant(direction, size, got, sock.getsockopt(socket.SOL_SOCKET, plain), forced)


def _granted(sock: socket.socket, option: int) -> int:
    reported = sock.getsockopt(socket.SOL_SOCKET, option)
    return reported // 2 if sys.platform.startswith("linux") else reported
