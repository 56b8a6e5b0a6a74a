"""What a loop process asks of the OS, and that it reports what it got.

Run in real child processes with real limits (util-linux's ``prlimit`` and ``setpriv``), so
the capability and the rlimit are the kernel's, not a patched function's.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys

import pytest

from rlbridge.hrt.rtenv import prepare_hrt_process, thread_scheduling

PROBE = "from rlbridge.hrt.rtenv import prepare_hrt_process as p; print(p(True))"


def _probe(*prefix: str) -> dict[str, str]:
    out = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    result: dict[str, str] = ast.literal_eval(out.strip())
    return result


def test_no_lock_asked_is_reported_as_no() -> None:
    assert prepare_hrt_process(False)["mlockall"] == "no"


@pytest.mark.skipif(not (shutil.which("prlimit") and shutil.which("setpriv")),
                    reason="needs util-linux's prlimit and setpriv")
def test_a_capped_memory_lock_is_skipped_not_risked() -> None:
    """Without CAP_IPC_LOCK and with a finite RLIMIT_MEMLOCK, MCL_FUTURE could later fail an
    allocation inside the loop: the set-up must skip it and say why."""
    info = _probe("prlimit", "--memlock=65536:65536", "setpriv", "--bounding-set",
                  "-ipc_lock")
    assert info["mlockall"] == "skipped: no CAP_IPC_LOCK and RLIMIT_MEMLOCK is 65536 bytes"


@pytest.mark.skipif(os.geteuid() != 0, reason="needs CAP_IPC_LOCK (root)")
def test_with_the_capability_memory_is_locked() -> None:
    info = _probe()
    assert info["mlockall"] == "yes"
    assert info["timer_slack"] == "1 ns"


def test_thread_scheduling_names_policy_cpus_and_interval() -> None:
    now = thread_scheduling()
    assert str(now["policy"]).startswith(("SCHED_OTHER nice", "SCHED_FIFO", "SCHED_RR"))
    assert now["cpus"] == "any" or all(c.isdigit() for c in str(now["cpus"]).split(","))
    assert now["switch_interval"] == sys.getswitchinterval()
