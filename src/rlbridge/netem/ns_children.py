"""The processes a link started in its namespaces, and their end when the link closes.

A namespace cannot be deleted cleanly while something still runs in it, so the link ends what
it started itself (terminate, then kill after a grace period) and then whatever else was left
running in its namespaces, before it deletes them.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Sequence
from typing import Any

from rlbridge.netem.netns import exec_argv, namespace_pids, terminate_pids

CHILD_GRACE_S = 2.0


class NamespaceChildren:
    """Processes started through one link; owned by it and ended by its teardown."""

    def __init__(self) -> None:
        self._procs: list[subprocess.Popen[Any]] = []

    def popen(self, namespace: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` in ``namespace`` and keep it, to be terminated by :meth:`terminate`."""
        proc: subprocess.Popen[Any] = subprocess.Popen(exec_argv(namespace, argv), **kwargs)
        self._procs.append(proc)
        return proc

    def terminate(self) -> None:
        """Terminate every child still running, then kill those that outlive the grace."""
        running = [p for p in self._procs if p.poll() is None]
        for proc in running:
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()
        for proc in running:
            try:
                proc.wait(timeout=CHILD_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._procs.clear()


def terminate_namespace_processes(names: Sequence[str]) -> None:
    """End whatever still runs in the namespaces ``names`` (this process excepted)."""
    for name in names:
        pids = [pid for pid in namespace_pids(name) if pid != os.getpid()]
        if pids:
            terminate_pids(pids, CHILD_GRACE_S)
