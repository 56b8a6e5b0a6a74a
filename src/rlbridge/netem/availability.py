"""Can the emulator run on this machine?  One human-readable reason if not.

Tests skip with this reason and the CLI prints it as its single error line, so each
reason says what is missing and how to get it.  The last check really creates a
namespace with a TUN device in it (and removes it), because containers often have
``/dev/net/tun`` and root but forbid ``setns`` or ``TUNSETIFF``.
"""

from __future__ import annotations

import os
import shutil
import sys

from rlbridge.netem.netns import (
    NetnsError,
    create_namespace,
    delete_namespace,
    namespace_name,
    new_run_token,
)
from rlbridge.netem.tun import TUN_DEVICE, open_tun


def emulator_unavailable_reason() -> str | None:
    """None if :class:`~rlbridge.netem.link.EmulatedLink` can run here, else why not."""
    if not sys.platform.startswith("linux"):
        return f"needs Linux network namespaces (this is {sys.platform})"
    if os.geteuid() != 0:
        return (
            f"needs root to create network namespaces and TUN devices "
            f"(running as uid {os.geteuid()}); run it with sudo"
        )
    if shutil.which("ip") is None:
        return "'ip' from iproute2 is not installed (apt-get install iproute2)"
    if not os.path.exists(TUN_DEVICE):
        return (
            f"{TUN_DEVICE} does not exist (load the 'tun' kernel module, or give the "
            f"container --device {TUN_DEVICE})"
        )
    return _probe()


def _probe() -> str | None:
    name = namespace_name(new_run_token(), "probe")
    try:
        create_namespace(name)
    except NetnsError as exc:
        return f"cannot create a network namespace: {exc}"
    try:
        os.close(open_tun(name, "rlbprobe0"))
    except OSError as exc:
        return f"cannot create a TUN device inside a network namespace: {exc}"
    finally:
        delete_namespace(name)
    return None
