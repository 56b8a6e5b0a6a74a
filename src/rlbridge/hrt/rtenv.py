"""What an HRT loop's process and thread were actually given, and the process-wide set-up.

Priorities and memory locking are requests the OS may refuse (no ``CAP_SYS_NICE``, no
``CAP_IPC_LOCK``). A loop that silently ran as an ordinary thread is the worst outcome, so
the set-up reports what held and the loop records its own scheduling from inside itself,
where it is true, not where it was asked for.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource
import sys

__all__ = ["prepare_hrt_process", "thread_scheduling"]

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_PR_SET_TIMERSLACK = 29
_CAP_IPC_LOCK = 14


def _may_lock_everything() -> str | None:
    """``None`` if locking all present and future memory is safe here, else why not.

    Without ``CAP_IPC_LOCK`` the locked total is capped by ``RLIMIT_MEMLOCK``; an
    ``mlockall(MCL_FUTURE)`` that fits today would turn a later allocation past the cap into
    a ``MemoryError`` in the loop, which is worse than a page fault.
    """
    try:
        with open("/proc/self/status") as status:
            caps = next(line for line in status if line.startswith("CapEff:"))
        if int(caps.split()[1], 16) >> _CAP_IPC_LOCK & 1:
            return None
    except (OSError, StopIteration, ValueError):
        pass
    soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft == resource.RLIM_INFINITY:
        return None
    return f"skipped: no CAP_IPC_LOCK and RLIMIT_MEMLOCK is {soft} bytes"


def prepare_hrt_process(mlock: bool) -> dict[str, str]:
    """Lock the process's memory (``mlock``) and set a 1 ns timer slack; say what held.

    Memory is locked only where the lock cannot later fail an allocation
    (``CAP_IPC_LOCK``, or no ``RLIMIT_MEMLOCK``); otherwise the report says it was skipped.

    ``mlockall(MCL_CURRENT | MCL_FUTURE)`` keeps the loop's pages resident (no page fault on
    a cold page mid-cycle); the timer slack stops the kernel from coalescing the loop's
    wake-up with others' (real-time threads get no slack anyway; this covers a refused
    priority). Both are process-wide, which is why the loop's own process is where they
    belong.
    """
    info: dict[str, str] = {}
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    except OSError as exc:  # pragma: no cover  no C library to load (not Linux)
        return {"mlockall": f"unavailable ({exc})", "timer_slack": "default"}
    refused = _may_lock_everything() if mlock else "no"
    if refused is None:
        ok = libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0
        info["mlockall"] = "yes" if ok else f"refused ({os.strerror(ctypes.get_errno())})"
    else:
        info["mlockall"] = refused
    slack = libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0
    info["timer_slack"] = "1 ns" if slack else "default"
    return info


def thread_scheduling() -> dict[str, str | float]:
    """The calling thread's policy, CPUs and the interpreter's switch interval, right now."""
    try:
        policy = os.sched_getscheduler(0)
        prio = os.sched_getparam(0).sched_priority
        names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO",
                 os.SCHED_RR: "SCHED_RR"}
        if policy == os.SCHED_OTHER:
            text = f"SCHED_OTHER nice {os.getpriority(os.PRIO_PROCESS, 0)}"
        else:
            text = f"{names.get(policy, str(policy))} {prio}"
        cpus = sorted(os.sched_getaffinity(0))
        where = "any" if len(cpus) == os.cpu_count() else ",".join(map(str, cpus))
    except (AttributeError, OSError):
        text, where = "unknown", "unknown"
    return {"policy": text, "cpus": where, "switch_interval": sys.getswitchinterval()}
