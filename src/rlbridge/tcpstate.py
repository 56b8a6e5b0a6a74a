"""Is a TCP connection backed up? The kernel's view, for latest-value delivery.

Latest-value channels (docs/policies.md) hold back values while the connection cannot take
them promptly and send only the newest once it can. "Cannot" is read from the kernel, not
guessed from timing: a connection is *congested* when

* the kernel holds bytes it has not sent yet (``SIOCOUTNSQ``): the congestion window is
  full, or Nagle waits for an acknowledgement;
* the kernel's congestion-avoidance state is not *Open* (``TCP_INFO`` ``tcpi_ca_state``):
  it saw duplicate acknowledgements or is recovering a loss, so anything written now
  queues behind a retransmission and reaches the reader in a burst; or
* more than ``max_unacked`` bytes are sent but unacknowledged (``SIOCOUTQ`` minus unsent).

Each check is one system call on the socket's descriptor. Linux only; elsewhere (or on an
error) the connection counts as not congested, so the policy degrades to plain delivery.
"""

from __future__ import annotations

import fcntl
import socket
import struct
import sys
from typing import Protocol

SIOCOUTQ = 0x5411  # bytes in the send queue, sent-unacknowledged plus unsent
SIOCOUTNSQ = 0x894B  # bytes in the send queue not yet sent
TCP_CA_OPEN = 0
#: Unacknowledged bytes beyond which a connection counts as backed up by default.
MAX_UNACKED = 16 << 10
_LINUX = sys.platform.startswith("linux")
_INT = struct.Struct("i")


class HasFileno(Protocol):
    def fileno(self) -> int: ...


def send_queue(sock: HasFileno) -> tuple[int, int]:
    """``(queued, unsent)`` bytes of a TCP socket's kernel send queue."""
    fd = sock.fileno()
    buf = bytearray(4)
    fcntl.ioctl(fd, SIOCOUTQ, buf)
    queued = _INT.unpack(buf)[0]
    fcntl.ioctl(fd, SIOCOUTNSQ, buf)
    return queued, _INT.unpack(buf)[0]


def ca_state(sock: socket.socket | HasFileno) -> int:
    """The kernel's congestion-avoidance state (0 Open, 1 Disorder, 2 CWR, 3 Recovery, 4 Loss)."""
    getsockopt = getattr(sock, "getsockopt", None)
    if getsockopt is None:
        return TCP_CA_OPEN
    info: bytes = getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)
    return info[1] if len(info) > 1 else TCP_CA_OPEN


def congested(sock: socket.socket | HasFileno, max_unacked: int = MAX_UNACKED) -> bool:
    """True while the connection is backed up (module docstring)."""
    if not _LINUX:
        return False
    try:
        queued, unsent = send_queue(sock)
        if unsent > 0 or queued - unsent > max_unacked:
            return True
        return queued > 0 and ca_state(sock) != TCP_CA_OPEN
    except (OSError, ValueError):  # closed meanwhile: the caller learns it from the write
        return False
