"""Is a TCP connection backed up? The kernel's view, for latest-value delivery.

Latest-value channels (docs/policies.md) hold back values while the connection cannot take
them promptly and send only the newest once it can. "Cannot" is read from the kernel, not
guessed from timing: a connection is *congested* when

* the kernel holds bytes it has not sent yet (``SIOCOUTNSQ``): the receive or congestion
  window is full, or Nagle waits for an acknowledgement, so a value written now waits
  behind them; or
* more than ``max_unacked`` bytes are sent but unacknowledged (``SIOCOUTQ`` minus unsent).

Deliberately *not* a reason: the kernel recovering a loss (``TCP_INFO`` ``tcpi_ca_state``
not Open). Holding new data back then starves the loss detection of the duplicate
acknowledgements new segments would cause, so recovery falls back to retransmission
timeouts with exponential backoff: measured over the emulated link (10% loss, 10 ms each
way, tests/netem/test_policies_netem.py) that raised the worst age from ~70 ms to 1.3 s.
The burst a retransmission releases is collapsed at the receiver instead, which keeps only
the newest value of what arrives together.

Each check is one system call on the socket's descriptor. Linux only; elsewhere (or on an
error) the connection counts as not congested, so the policy degrades to plain delivery.
"""

from __future__ import annotations

import fcntl
import struct
import sys
from typing import Protocol

SIOCOUTQ = 0x5411  # bytes in the send queue, sent-unacknowledged plus unsent
SIOCOUTNSQ = 0x894B  # bytes in the send queue not yet sent
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


def congested(sock: HasFileno, max_unacked: int = MAX_UNACKED) -> bool:
    """True while the connection is backed up (module docstring)."""
    if not _LINUX:
        return False
    try:
        queued, unsent = send_queue(sock)
        return unsent > 0 or queued - unsent > max_unacked
    except (OSError, ValueError):  # closed meanwhile: the caller learns it from the write
        return False
